"""pycolmap, loaded so that the command's SIGTERM handling survives it.

Importing pycolmap installs glog's handlers of fatal signals, SIGTERM among them, over the handler the CLI set
(:func:`plantsplat.cli.sigterm_as_interrupt`): a SIGTERM (``kill``, ``timeout``, a scheduler) then ended a run with a
stack trace instead of the Ctrl-C path (stage record left resumable, one line, exit 143). :func:`load_pycolmap` puts
the Python handler back (Python keeps its own record of it, which the import does not change); a later
``import pycolmap`` finds the module loaded and changes nothing. The poses stage, whose modules import pycolmap, calls it
when it starts; the modules that read a COLMAP model in the other stages load pycolmap through it.

Example:
    >>> pycolmap = load_pycolmap()
    >>> hasattr(pycolmap, "Reconstruction")
    True
"""

from __future__ import annotations

import signal
import threading


def load_pycolmap():
    """The pycolmap module, imported with this process's SIGTERM handler kept (in the main thread)."""
    handler = signal.getsignal(signal.SIGTERM)
    import pycolmap  # deferred: heavy, and its import replaces the SIGTERM handler, put back below

    if handler is not None and threading.current_thread() is threading.main_thread():
        signal.signal(signal.SIGTERM, handler)
    return pycolmap
