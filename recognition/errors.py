"""Exception root of the ``recognition`` package."""


class RecognitionError(Exception):
    """Root of every error raised by ``recognition``."""


class CloudError(RecognitionError, ValueError):
    """A point cloud, depth image or cloud file is unusable (empty, wrong shape, unreadable)."""


class ModelError(RecognitionError, ValueError):
    """A model database or a model source (mesh, cloud, recording) is missing or inconsistent."""
