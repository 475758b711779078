"""Off-screen pyvista plotting shared by every preview and render writer.

VTK tries an X display first and logs a warning to stderr when there is none (the normal
case on servers and in CI); :func:`offscreen_plotter` silences that and always renders off
screen, so previews work headless without noise.
"""

from __future__ import annotations

__all__ = ["offscreen_plotter"]

_quiet = False


def offscreen_plotter(window_size=(800, 800), **kwargs):
    """A ``pyvista.Plotter(off_screen=True)`` with VTK's display warnings silenced."""
    global _quiet
    import pyvista as pv

    if not _quiet:
        try:
            from vtkmodules.vtkCommonCore import vtkLogger, vtkObject

            vtkLogger.SetStderrVerbosity(vtkLogger.VERBOSITY_OFF)
            vtkObject.GlobalWarningDisplayOff()
        except ImportError:  # older VTK layouts: the warning is cosmetic
            pass
        _quiet = True
    return pv.Plotter(off_screen=True, window_size=list(window_size), **kwargs)
