"""The package's exceptions: one root, so a caller can catch everything supramodal raises on purpose.

Every error the project raises deliberately (the model, the drivers, replay, the node, the
command line) derives from :class:`SupramodalError`; the command line prints those as one
line, and anything else as a bug, with its traceback. The tree::

    SupramodalError
     +-- InputError (also ValueError): an argument, a block of samples or a file's content is refused
     |    +-- node.scene.specs.SceneError, supramodal.model.ModelError, replay.errors.ReplayError, ...
     +-- drivers.base.DriverError: a device or stream failed (DeviceUnavailable, DriverClosed, ...)
     +-- node.runtime.ringbuffer.RingBufferError
     +-- node.runtime.graph.NodeError (also RuntimeError): a thread of the node failed
     +-- StreamEndedError (also RuntimeError): a block fed to a stream after its finish()
     +-- parallel.WorkerLost (also RuntimeError): a worker process ended in the middle of its work

The leaf classes live beside the code that raises them; this module holds only the root and
the kinds every layer shares, so that any layer may import it without importing anything else.
"""

from __future__ import annotations


class SupramodalError(Exception):
    """Root of every error the project raises on purpose; its message says what is wrong and the fix."""


class InputError(SupramodalError, ValueError):
    """Bad input: an argument, a block of samples or a file's content does not fit. Also a ValueError."""


class StreamEndedError(SupramodalError, RuntimeError):
    """A block was fed to a streaming object (peak extractor, pipeline) after its ``finish()``.

    A stream that has ended takes no more samples; make a new one, or ``reset()`` it. Also a
    RuntimeError.
    """


class SupramodalWarning(UserWarning):
    """Root of the project's warnings: something was accepted but deserves the user's attention."""
