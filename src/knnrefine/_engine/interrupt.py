"""Ctrl-C while kernels run.

Python's own SIGINT handler raises KeyboardInterrupt wherever the interpreter next checks for
signals. Inside a compiled kernel that can be a C-API call numba makes on the way (the
exception is then set while the kernel returns normally: "SystemError: CPUDispatcher(...)
returned a result with an exception set"), and an exception set there can also be swallowed,
so the interrupt is lost and the run goes on. ``Interrupts`` replaces the default handler
while a run is in progress by one that only records the signal; ``check()`` raises
KeyboardInterrupt between kernel calls (the driver's calls last about 50 ms). A handler the
user installed, or a run outside the main thread, is left alone.
"""

import signal
import threading


class Interrupts:
    """Context manager: records Ctrl-C while kernels run; ``check()`` raises it."""

    def __init__(self):
        self.hit = False
        self._old = None

    def _record(self, signum, frame):
        self.hit = True

    def __enter__(self):
        if (
            threading.current_thread() is threading.main_thread()
            and signal.getsignal(signal.SIGINT) is signal.default_int_handler
        ):
            self._old = signal.signal(signal.SIGINT, self._record)
        return self

    def check(self):
        """Raise KeyboardInterrupt if Ctrl-C was pressed since the last check."""
        if self.hit:
            self.hit = False
            raise KeyboardInterrupt

    def __exit__(self, kind, value, traceback):
        if self._old is not None:
            signal.signal(signal.SIGINT, self._old)
            self._old = None
        if kind is None:
            self.check()
        return False
