"""Shared pytest fixtures and hooks."""

import importlib.util
from pathlib import Path

import pytest

STUDIES = Path(__file__).resolve().parents[1] / "studies"


@pytest.fixture(scope="session")
def bench_module():
    """Import a study script of ``studies/`` (not a package) by name: ``bench_module("paper_table")``."""

    def load(name):
        spec = importlib.util.spec_from_file_location(name, STUDIES / f"{name}.py")
        module = importlib.util.module_from_spec(spec)
        spec.loader.exec_module(module)
        return module

    return load


@pytest.fixture(scope="session")
def gl_ctx():
    """One headless OpenGL 3.3 context (EGL) for the session; tests fail, never skip, without it."""
    from prt.runtime.errors import GLContextError
    from prt.runtime.gl import create_context

    try:
        ctx, reason = create_context(), ""
    except GLContextError as exc:
        ctx, reason = None, str(exc)
    if ctx is None:  # failing outside the except block keeps the report to one line
        pytest.fail(reason, pytrace=False)
    yield ctx
    ctx.release()


@pytest.hookimpl(wrapper=True)
def pytest_runtest_call(item):
    """Fail a test that used ``gl_ctx`` if it left an OpenGL error behind."""
    ctx = getattr(item, "funcargs", {}).get("gl_ctx")
    try:
        result = yield
    finally:
        # Reading the error also clears it, so a failed test never blames the next one.
        error = ctx.error if ctx is not None else "GL_NO_ERROR"
    if error != "GL_NO_ERROR":
        pytest.fail(f"{item.nodeid} left OpenGL error {error}", pytrace=False)
    return result
