"""What a :class:`~prt.runtime.renderer.Renderer` holds in GL and ONNX Runtime, and releasing it once.

:class:`RendererResources` refers to no Renderer, so ``weakref.finalize`` can release a Renderer
that is never closed when it is collected; :func:`make_current` is how every Renderer call makes
its context current first.
"""

from __future__ import annotations

import contextlib
import threading

import moderngl

from .gl import bind_framebuffer

__all__ = ["RendererResources", "make_current"]


def make_current(ctx: moderngl.Context) -> None:
    """Make ``ctx`` the thread's current GL context and leave it current (moderngl's ``with ctx``
    would restore the previous one on exit, which may be a context released since)."""
    ctx.__enter__()


class RendererResources:
    """What a Renderer holds in GL and ONNX Runtime, released once: by ``close()`` or, for a
    Renderer never closed, by ``weakref.finalize`` when it is collected (so it refers to no Renderer)."""

    def __init__(self, ctx: moderngl.Context, own_ctx: bool, bound_fbo) -> None:
        self.ctx, self.own_ctx, self.bound_fbo = ctx, own_ctx, bound_fbo
        self.owner = threading.get_ident()
        self.objects: list = []
        self.backends: dict = {}  # name -> TransferBackend
        self.released = False

    def keep(self, obj):
        self.objects.append(obj)
        return obj

    def release(self, rebind: bool) -> None:
        if self.released:
            return
        if threading.get_ident() != self.owner:
            # Collected in another thread (one of ONNX Runtime's, say), where the context is not
            # current: GL calls would go nowhere.  The objects die with the context at exit.
            return
        self.released = True
        # close() rebinds the framebuffer bound at creation; collection (at any moment, maybe during
        # another renderer's frame on a shared context) rebinds only if one of ours is bound.
        ours = {id(o) for o in self.objects}
        # Release in our context (another renderer's may be current).  close() leaves it current;
        # collection, which may come during another renderer's frame, gives the current one back.
        if rebind:
            make_current(self.ctx)
        with contextlib.nullcontext() if rebind else self.ctx:
            for backend in self.backends.values():
                backend.release()
            self.backends.clear()
            if rebind or (self.ctx.fbo is not None and id(self.ctx.fbo) in ours):
                bind_framebuffer(self.ctx, self.bound_fbo)
            for obj in reversed(self.objects):
                obj.release()
        self.objects.clear()
        if self.own_ctx:
            self.ctx.release()
