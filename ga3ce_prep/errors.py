"""Error classes. Each message names the file or key at fault and the fix."""


class Ga3ceError(Exception):
    """Base class: the CLI prints these as one clear message, without a traceback."""


class DatasetFormatError(Ga3ceError):
    """A structural problem with a dataset on disk (layout, annotation columns): stops a run before any work."""


class FrameError(Ga3ceError):
    """A problem with one frame (missing image, no depth at the head): becomes a failure record."""


class ConfigError(Ga3ceError):
    """A pipeline file or option is invalid."""


class ModelFileError(Ga3ceError):
    """A model file is missing or does not match the interface it should have."""


class StoreError(Ga3ceError):
    """A store is missing, incomplete, locked or of another schema version."""
