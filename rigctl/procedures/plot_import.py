"""matplotlib imported on a thread while a solve computes, for the plots drawn after it.

The plots are drawn after the result is recorded (``SolveContext.defer``), but a
re-solve's process (``rigctl solve``) ends only when they are: importing matplotlib's
figure and Agg backend there cost about 0.45 s of the 0.9 s the active-camera plots took.
That import is Python executing modules; the solve's first stages spend their time in
OpenCV and numpy calls that release the interpreter, so the import overlaps them nearly
for free. Without the ``plots`` extra nothing happens here: the deferred plot reports the
missing extra itself.
"""

from __future__ import annotations

import threading


def _import_matplotlib() -> None:
    try:
        import matplotlib.backends.backend_agg
        import matplotlib.figure  # noqa: F401
    except ImportError:
        pass


def import_matplotlib_in_background() -> threading.Thread:
    """Start importing matplotlib's ``Figure`` and Agg backend on a daemon thread (a
    second import of the same modules waits for this one, Python's import lock)."""
    thread = threading.Thread(target=_import_matplotlib, name="import matplotlib", daemon=True)
    thread.start()
    return thread
