"""Deringing windows on the SH lighting (issue 12, item 5): error against the env map itself.

usage: python studies/dering.py [--envmaps NAME|PATH ...] [--points N] [--exponent E] [--json OUT]

``prt-bench``'s reference shades ray-traced transfer with the same 4-band lighting as the
renderer, so it cannot see the lighting's own ringing.  Here the truth integrates the env map
directly (area-averaged to 64 x 128 texels) for unoccluded points: diffuse
``(1/pi) int L max(0, n.w) dw`` and glossy ``int L max(0, n.w) (e+1)/(2 pi) max(0, r.w)^e dw``,
the quantities :func:`prt.runtime.shading.shade` approximates with the unshadowed transfer.
Normals are uniform on the sphere, view directions uniform over each normal's hemisphere.
Per env map, material and window: relative MAE of linear radiance, PSNR of the tone-mapped
values (exposure 1, as the renderer), and the share of points whose SH radiance is negative in
some channel (clamped towards black).
"""

from __future__ import annotations

import argparse
import json
import sys

import numpy as np

from prt.runtime import sh
from prt.runtime.envmap import read_envmap
from prt.runtime.envmaps import BUNDLED_ENVMAPS, bundled_envmap_path
from prt.runtime.shading import Lighting, Material, shade, tonemap

WINDOWS = (None, ("hanning", 8.0), ("hanning", 6.0), ("hanning", 5.0), ("hanning", 4.0), ("lanczos", 6.0), ("lanczos", 4.0))
ALBEDO = (0.7, 0.7, 0.7)


def _downsample(image: np.ndarray, height: int = 64) -> np.ndarray:
    """Area average to ``height`` x 2 ``height`` texels (energy kept: every texel covers whole source texels)."""
    h, w = image.shape[:2]
    f = h // height
    image = image[: height * f, : 2 * height * f]
    return image.reshape(height, f, 2 * height, image.shape[1] // (2 * height), 3).mean(axis=(1, 3))


def _points(n: int, seed: int = 0) -> tuple[np.ndarray, np.ndarray]:
    rng = np.random.default_rng(seed)
    normals = rng.normal(size=(n, 3))
    normals /= np.linalg.norm(normals, axis=1, keepdims=True)
    views = rng.normal(size=(n, 3))
    views /= np.linalg.norm(views, axis=1, keepdims=True)
    views *= np.sign(np.sum(views * normals, axis=1, keepdims=True))  # the eye above the surface
    return normals, views


def truth(image: np.ndarray, normals: np.ndarray, views: np.ndarray, exponent: float) -> tuple[np.ndarray, np.ndarray]:
    """(diffuse (N, 3), glossy spec (N, 3)) integrated over the env map's texels."""
    small = _downsample(image)
    h, w = small.shape[:2]
    dirs = sh.envmap_directions(h, w).reshape(-1, 3)
    radiance = small.reshape(-1, 3) * sh.texel_solid_angles(h, w).reshape(-1, 1)
    r = 2 * np.sum(normals * views, axis=1, keepdims=True) * normals - views
    diffuse, spec = np.empty_like(normals), np.empty_like(normals)
    for i in range(0, len(normals), 2048):
        cos_n = np.maximum(normals[i : i + 2048] @ dirs.T, 0.0)
        lobe = (exponent + 1) / (2 * np.pi) * np.maximum(r[i : i + 2048] @ dirs.T, 0.0) ** exponent
        diffuse[i : i + 2048] = cos_n @ radiance / np.pi
        spec[i : i + 2048] = (cos_n * lobe) @ radiance
    return diffuse, spec


def measure(path, n: int, exponent: float, specular: float = 0.3) -> dict:
    image = read_envmap(path)
    coeffs = sh.project_envmap(image, 4)
    normals, views = _points(n)
    diffuse, spec = truth(image, normals, views, exponent)
    transfer = sh.unshadowed_transfer(normals, 4)
    albedo = np.asarray(ALBEDO)
    materials = {
        "diffuse": (Material(albedo=ALBEDO), albedo * diffuse),
        "glossy": (Material(kind="glossy", albedo=ALBEDO, specular=(specular,) * 3, exponent=exponent), albedo * diffuse + specular * spec),
    }
    out = {}
    for window in WINDOWS:
        lighting = Lighting.from_sh(coeffs, window=window)
        label = "none" if window is None else f"{window[0]}:{window[1]:g}"
        for name, (material, exact) in materials.items():
            raw = _unclamped(transfer, normals, views, lighting, material)
            got = np.maximum(raw, 0.0)
            err = np.abs(got - exact).mean() / max(np.abs(exact).mean(), 1e-12)
            a, b = tonemap(got), tonemap(exact)
            psnr = float(10 * np.log10(1.0 / max(np.mean((a - b) ** 2), 1e-20)))
            out[f"{name} {label}"] = {"rel_mae": round(float(err), 4), "psnr": round(psnr, 2),
                                      "negative_share": round(float((raw < 0).any(axis=1).mean()), 4),
                                      "black_share": round(float((raw <= 0).all(axis=1).mean()), 4)}  # fmt: skip
    return out


def _unclamped(transfer, normals, views, lighting, material) -> np.ndarray:
    """``shade`` before its clamp at 0: shade of +T minus shade's clamp is lost, so recompute the sum here."""
    radiance = np.asarray(material.albedo) * (transfer @ lighting.sh)
    if material.kind == "glossy":
        n = lighting.sh.shape[0]
        lobe = sh.band_factors_to_coeff_scale(material.lobe_band_factors(lighting.bands))
        r = 2 * np.sum(normals * views, axis=1, keepdims=True) * normals - views
        transferred = (transfer @ lighting.light_matrix.reshape(3 * n, n).T).reshape(-1, 3, n)
        radiance = radiance + np.asarray(material.specular) * np.pi * np.einsum("pck,pk->pc", transferred, sh.basis(r, lighting.bands) * lobe)
    assert np.allclose(np.maximum(radiance, 0), shade(transfer, normals, views, lighting, material), atol=1e-4)
    return radiance


def main(argv=None) -> int:
    p = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    p.add_argument("--envmaps", nargs="+", default=[*BUNDLED_ENVMAPS, "../shared/data/envmaps/venice_sunset_1k.hdr"])
    p.add_argument("--points", type=int, default=20000)
    p.add_argument("--exponent", type=float, default=32.0)
    p.add_argument("--json", default=None)
    args = p.parse_args(argv)
    results = {}
    for name in args.envmaps:
        path = bundled_envmap_path(name) if name in BUNDLED_ENVMAPS else name
        results[name] = measure(path, args.points, args.exponent)
        print(f"{name} (exponent {args.exponent:g}):")
        for label, r in results[name].items():
            print(f"  {label:>20}: rel MAE {r['rel_mae']:.4f}  PSNR {r['psnr']:6.2f} dB  negative {100 * r['negative_share']:5.2f} %  "
                  f"black {100 * r['black_share']:5.2f} %")  # fmt: skip
    if args.json:
        with open(args.json, "w") as f:
            json.dump(results, f, indent=1)
    return 0


if __name__ == "__main__":
    sys.exit(main())
