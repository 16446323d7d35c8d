"""Fits run at once on threads of one process (the build's fit stage and refinement rounds): a fit's weights
are the same bytes as the same fit run alone, because the network's seeded construction is serialised
(``prt.train.networks.fit.seeded``) and nothing after it draws from torch's process-wide generator."""

from __future__ import annotations

import threading

import numpy as np
import pytest

torch = pytest.importorskip("torch")

from prt.train.networks.fit import FIT_THREADS, FitSettings, fit_segment, seeded  # noqa: E402
from prt.train.networks.grid_encoding import GridArchitecture, fit_grid_segment  # noqa: E402
from prt.train.networks.network import Architecture  # noqa: E402


def test_seeded_construction_is_not_interleaved_with_another():
    """While one construction runs (it waits for another thread's seeding, which the lock keeps out), its draws
    are those of its own seed alone; without the lock the other thread's reseeding would land between them."""
    inside, entered = threading.Event(), threading.Event()
    drawn = {}

    def slow():  # draws, gives the other thread 0.3 s to reseed the generator, draws again
        inside.set()
        first = torch.rand(4)
        entered.wait(timeout=0.3)
        return torch.cat([first, torch.rand(4)])

    def other():
        drawn["other"] = seeded(1, lambda: (entered.set(), torch.rand(4))[1])

    t = threading.Thread(target=other)
    with torch.random.fork_rng():
        torch.manual_seed(123)
        runner = threading.Thread(target=lambda: drawn.__setitem__("slow", seeded(0, slow)))
        runner.start()
        inside.wait(timeout=10)
        t.start()  # while the runner holds the lock
        runner.join()
        t.join()
        torch.manual_seed(0)
        alone = torch.rand(8)
        torch.manual_seed(1)
        other_alone = torch.rand(4)
    assert torch.equal(drawn["slow"], alone)
    assert torch.equal(drawn["other"], other_alone)


def _data(seed, m=600):
    rng = np.random.default_rng(seed)
    p = rng.uniform(-1, 1, (m, 3)).astype(np.float32)
    n = rng.normal(size=(m, 3)).astype(np.float32)
    n /= np.linalg.norm(n, axis=1, keepdims=True)
    t = (0.1 * np.sin(3.0 * p @ rng.normal(size=(3, 16)))).astype(np.float32)
    return p, n, t


@pytest.mark.parametrize("arch", [Architecture(hidden=16, layers=2, pos_freqs=3), GridArchitecture(levels=2, features=2, log2_table=8, max_resolution=16, hidden=16, layers=1)],
                         ids=["frequency", "grid"])
def test_fits_on_threads_at_once_equal_the_same_fits_alone(arch):
    p, n, t = _data(0)
    bounds = np.stack([p.min(axis=0), p.max(axis=0)])
    settings = FitSettings(steps=60, batch=128, lr=0.01, loss="l2")
    fit = fit_segment if isinstance(arch, Architecture) else fit_grid_segment

    def run(seed_data):
        q, m, u = _data(seed_data)
        return fit(q[:500], m[:500], u[:500], q[500:], m[500:], u[500:], arch, bounds, settings)

    before = torch.get_num_threads()
    torch.set_num_threads(FIT_THREADS)
    try:
        alone = [run(s) for s in range(4)]
        results = [None] * 4
        threads = [threading.Thread(target=lambda s=s: results.__setitem__(s, run(s))) for s in range(4)]
        for th in threads:
            th.start()
        for th in threads:
            th.join()
    finally:
        torch.set_num_threads(before)
    for a, b in zip(alone, results):
        for x, y in zip(a.model.state_dict().values(), b.model.state_dict().values()):
            assert np.array_equal(x.numpy(), y.numpy())
