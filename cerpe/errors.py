"""The root of every exception ``cerpe`` raises on purpose.

Each module defines its own subclass (``GeometryError``, ``SceneError``,
``ManifestError``...); the command line catches :class:`CerpeError` and prints
its message (which names the file, field or robot at fault) without a traceback.
"""


class CerpeError(Exception):
    """Base class of all deliberate ``cerpe`` errors."""
