"""One ``with``-block protocol for objects that hold something until they are done.

A subclass says what entering starts (:meth:`Scoped.enter`, nothing by default) and
what leaving releases (:meth:`Scoped.leave`); leaving runs however the block ends.
"""

from __future__ import annotations

from types import TracebackType
from typing import Self


class Scoped:
    """Base of objects used as ``with obj:``: :meth:`enter` on entry, :meth:`leave` on exit."""

    def enter(self) -> None:
        """Start what the ``with`` block needs (nothing unless a subclass says so)."""

    def leave(self) -> None:
        """Release what the object holds; a subclass must say what."""
        raise NotImplementedError

    def __enter__(self) -> Self:
        self.enter()
        return self

    def __exit__(
        self,
        exc_type: type[BaseException] | None,
        exc: BaseException | None,
        traceback: TracebackType | None,
    ) -> None:
        self.leave()
