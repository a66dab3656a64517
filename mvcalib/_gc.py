"""Python's cyclic garbage collector, paused while mvcalib makes many objects that live on.

Importing mvcalib's modules (with Equinox, Optimistix and Lineax: some 200 classes) and tracing and
lowering a program make hundreds of thousands of objects. Python's collector counts them and, every
so many, walks all the objects the process holds (JAX's, the user's) looking for cycles: in vain
here, since what an import makes lives on and a trace's garbage is freed as its references go. At
the first `calibrate(..., refine=True)` of 1024 cameras, a fresh process spent 0.2 s (of the 1.3-2
s its main thread worked) in such walks; with the collector paused around its imports and traces,
0.04-0.05 s. It runs again afterwards as it would have (its next walk finds any cycle left), and a
user who turned it off finds it off.
"""

from __future__ import annotations

import contextlib
import gc


@contextlib.contextmanager
def collector_paused():
    """Pause the cyclic garbage collector (if it runs) for the block, and restart it after.

    >>> import gc
    >>> with collector_paused():
    ...     gc.isenabled()
    False
    >>> gc.isenabled()
    True
    """
    if not gc.isenabled():
        yield
        return
    gc.disable()
    try:
        yield
    finally:
        gc.enable()
