"""The package's exceptions: one root, so a caller can catch everything supramodal raises on purpose.

Every error the project raises deliberately (the model, the drivers, replay, the node, the
command line) derives from :class:`SupramodalError`; the command line prints those as one
line, and anything else as a bug, with its traceback. The tree::

    SupramodalError
     +-- InputError (also ValueError): an argument, a block of samples or a file's content is refused
     |    +-- node.scene.SceneError, supramodal.model.ModelError, replay.errors.ReplayError, ...
     +-- drivers.base.DriverError: a device or stream failed (DeviceUnavailable, DriverClosed, ...)
     +-- node.ringbuffer.RingBufferError
     +-- node.graph.NodeError (also RuntimeError): a thread of the node failed

The leaf classes live beside the code that raises them; this module holds only the root and
the kinds every layer shares, so that any layer may import it without importing anything else.
"""

from __future__ import annotations


class SupramodalError(Exception):
    """Root of every error the project raises on purpose; its message says what is wrong and the fix."""


class InputError(SupramodalError, ValueError):
    """Bad input: an argument, a block of samples or a file's content does not fit. Also a ValueError."""


class SupramodalWarning(UserWarning):
    """Root of the project's warnings: something was accepted but deserves the user's attention."""
