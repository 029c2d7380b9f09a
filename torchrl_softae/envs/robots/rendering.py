"""Offscreen OpenGL for MuJoCo, chosen only when something renders.

Nothing here runs at import: importing a robot never loads a GL library. The first render picks
the backend: ``MUJOCO_GL`` if the user set it (MuJoCo honoured it at import), else EGL, else
OSMesa, whichever system library exists; with neither, one line says what to install.
"""
from __future__ import annotations

import ctypes.util
import importlib
import os

__all__ = ["RenderingUnavailable", "offscreen_backend"]

_LIBRARIES = {"egl": "EGL", "osmesa": "OSMesa"}  # backend -> system library it needs


class RenderingUnavailable(RuntimeError):
    """No OpenGL backend for offscreen rendering on this machine."""


def offscreen_backend() -> str:
    """Make MuJoCo's ``Renderer`` use a working offscreen backend; returns its name."""
    from mujoco.rendering.classic import gl_context

    chosen = os.environ.get("MUJOCO_GL", "").lower().strip()
    if chosen:
        return chosen
    for backend, library in _LIBRARIES.items():
        if ctypes.util.find_library(library) is None:
            continue
        if os.environ.setdefault("PYOPENGL_PLATFORM", backend) != backend:
            continue  # PyOpenGL is pinned to another platform by the user
        try:
            gl_context.GLContext = importlib.import_module(f"mujoco.{backend}").GLContext
        except Exception:  # noqa: BLE001 -- a broken driver install: try the next backend
            os.environ.pop("PYOPENGL_PLATFORM", None)
            continue
        os.environ["MUJOCO_GL"] = backend
        return backend
    raise RenderingUnavailable(
        "no OpenGL backend for offscreen rendering: install EGL (apt-get install libegl1) or OSMesa "
        "(apt-get install libosmesa6), or set MUJOCO_GL"
    )
