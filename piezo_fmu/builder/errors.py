"""The build's error types."""
from __future__ import annotations

__all__ = ["BuildError"]


class BuildError(RuntimeError):
    """The build failed; the message says where and why."""
