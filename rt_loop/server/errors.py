"""The server's error: a module of its own, so that every part of the server
raises it without importing the others."""

__all__ = ["ServerError"]


class ServerError(RuntimeError):
    """The server cannot be set up or stopped; ``str()`` is one line naming the cause."""
