"""matplotlib imported on a thread while a live run moves, for the plots after its solve.

The plots are drawn after the result is recorded (``SolveContext.defer``), but the run
holds the rig until they are: importing matplotlib's figure and Agg backend cost about
0.45 s of the 0.9 s the active-camera plots took. A live run imports them while the rig
moves (``ActiveCamera.capture_work``). A re-solve does not: the import is Python
executing modules, and beside the solve's first stages it held the interpreter they
needed (the demo's run re-solved: loading the images 0.12 -> 0.34 s, to the result no
faster). Without the ``plots`` extra nothing happens here: the deferred plot reports the
missing extra itself.
"""

from __future__ import annotations

import threading

from rigctl.calib.active_plots import import_plot_modules


def import_matplotlib_in_background() -> threading.Thread:
    """Start importing matplotlib's ``Figure`` and Agg backend on a daemon thread (a
    second import of the same modules waits for this one, Python's import lock)."""
    thread = threading.Thread(target=import_plot_modules, name="import matplotlib", daemon=True)
    thread.start()
    return thread
