"""Progress reporting strategies passed to long computations (``progress=`` arguments).

A computation calls ``start(total, desc)``, then ``update(done)`` with the absolute amount done
(e.g. the simulated time reached), then ``close()``; ``note(message)`` says, in a line, what a
stage is about to do (what it will compute and why, before the wait), and ``stage(name)`` names
the part now running. ``start(..., uniform=False)`` says that the units of work differ in cost
(a render's stages), so that no time remaining is extrapolated from them. :class:`Progress` itself is silent; pass
:class:`TqdmProgress` for a progress bar (the CLI does).
"""
from __future__ import annotations

import logging

__all__ = ["Progress", "TqdmProgress"]

logger = logging.getLogger(__name__)


class Progress:
    """Silent progress reporter: the base class and the default."""

    def start(self, total: float, desc: str = "", uniform: bool = True) -> None:
        pass

    def stage(self, name: str) -> None:
        pass

    def update(self, done: float) -> None:
        pass

    def close(self) -> None:
        pass

    def note(self, message: str) -> None:
        pass


class TqdmProgress(Progress):
    """A tqdm progress bar (on stderr), shown only for runs longer than ``delay`` seconds."""

    def __init__(self, delay: float = 1.0, **tqdm_kwargs):
        self.delay = delay
        self.kwargs = tqdm_kwargs
        self._bar = None
        self._done = 0.0

    def start(self, total: float, desc: str = "", uniform: bool = True) -> None:
        from tqdm.auto import tqdm

        when = "[{elapsed}<{remaining}]" if uniform else "[{elapsed}]"
        self._bar = tqdm(total=float(total), desc=desc, delay=self.delay,
                         bar_format="{l_bar}{bar}| {n:.3g}/{total:.3g} " + when, **self.kwargs)
        self._desc = desc
        self._done = 0.0

    def stage(self, name: str) -> None:
        """Show ``name`` after the bar's description (the part now running)."""
        if self._bar is not None:
            # (no refresh of its own: a bar still within its delay stays unshown)
            self._bar.set_description(f"{self._desc}: {name}" if self._desc else name, refresh=False)

    def update(self, done: float) -> None:
        if self._bar is not None and done > self._done:
            self._bar.update(done - self._done)
            self._done = done

    def close(self) -> None:
        if self._bar is not None:
            self._bar.close()
            self._bar = None

    def note(self, message: str) -> None:
        """The line on stderr (above a bar that is shown) when stderr is a terminal, where a person
        waits for it; logged at INFO level (``-v``) in any case, so that a job's log can have it."""
        import sys

        from tqdm.auto import tqdm

        logger.info(message)
        if getattr(sys.stderr, "isatty", lambda: False)():
            tqdm.write(message, file=sys.stderr)
