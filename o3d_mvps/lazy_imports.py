"""Open3D's plotly viewer loaded on first use, so that ``import open3d`` skips plotly and Dash.

``import open3d`` imports ``open3d.visualization.draw_plotly``, which imports plotly's figure
classes and the Dash web framework: 0.3 of the 0.6 CPU s the import costs, on every command,
for a viewer the package never calls. :func:`defer_open3d_plotly` (run on import of
``o3d_mvps``, before anything imports Open3D) puts a stand-in module under that name: its
``draw_plotly``, ``draw_plotly_server`` and ``get_plotly_fig`` import the real module on their
first call and then are Open3D's own (``open3d.visualization.draw_plotly(...)`` works as
before, a moment slower the first time). Where Open3D is already imported, nothing changes.
"""

from __future__ import annotations

import importlib
import importlib.util
import sys
import types

#: the module put off, and the names ``open3d.visualization`` takes from it
PLOTLY_MODULE = "open3d.visualization.draw_plotly"
PLOTLY_NAMES = ("get_plotly_fig", "draw_plotly", "draw_plotly_server")


def defer_open3d_plotly() -> bool:
    """Put the stand-in for :data:`PLOTLY_MODULE` into ``sys.modules``; True where it was put,
    False where Open3D (or that module) is already imported or Open3D is not installed."""
    if "open3d" in sys.modules or PLOTLY_MODULE in sys.modules or importlib.util.find_spec("open3d") is None:
        return False
    stub = types.ModuleType(PLOTLY_MODULE, "Stand-in for Open3D's plotly viewer (o3d_mvps.lazy_imports): "
                                           "the real module loads on the first call of one of its functions.")
    stub.__o3d_mvps_stand_in__ = True
    for name in PLOTLY_NAMES:
        setattr(stub, name, _first_call(name))
    stub.__getattr__ = _other_name
    sys.modules[PLOTLY_MODULE] = stub
    return True


def open3d_plotly() -> types.ModuleType:
    """The real :data:`PLOTLY_MODULE`, imported now if only the stand-in was; its functions then
    replace the stand-in's in ``open3d.visualization``."""
    module = sys.modules.get(PLOTLY_MODULE)
    if module is not None and not getattr(module, "__o3d_mvps_stand_in__", False):
        return module
    sys.modules.pop(PLOTLY_MODULE, None)
    module = importlib.import_module(PLOTLY_MODULE)
    parent = sys.modules["open3d.visualization"]
    for name in PLOTLY_NAMES:  # loading the submodule bound its name in the parent: Open3D binds the functions
        setattr(parent, name, getattr(module, name))
    return module


def _other_name(attr: str):
    """Any other public name of the stand-in: the real module's (dunder names, which the import
    system and ``repr`` probe, are not looked up there)."""
    if attr.startswith("__"):
        raise AttributeError(f"module {PLOTLY_MODULE!r} (o3d_mvps's stand-in) has no attribute {attr!r}")
    return getattr(open3d_plotly(), attr)


def _first_call(name: str):
    """A function that imports the real module and calls its ``name``."""
    def call(*args, **kwargs):
        return getattr(open3d_plotly(), name)(*args, **kwargs)

    call.__name__ = call.__qualname__ = name
    call.__doc__ = f"Open3D's ``{name}``, imported on this first call (with plotly and Dash)."
    return call
