"""The one exception hierarchy of faceretarget.

Every error the library raises on purpose is a :class:`FaceRetargetError`. The
subclasses also derive from the closest built-in exception (``ValueError``,
``KeyError``, ``OSError``...) so code written against the standard library keeps
working. Messages say what was wrong *and* how to fix it.

::

    FaceRetargetError
    ├── InputError (ValueError)               bad arrays or model objects
    │   ├── ShapeError                        wrong rank, length or shape
    │   ├── NonFiniteError                    NaN / inf where not allowed
    │   ├── IndexRangeError                   indices outside their range
    │   ├── DegenerateGeometryError           zero-area / duplicate triangles ...
    │   ├── TopologyMismatchError             vertex or triangle counts disagree
    │   └── CorrespondenceError               two faces could not be matched reliably
    ├── UnknownNameError (KeyError)           a name (method, shape, format) not known
    ├── CapabilityError                       a method asked for what it cannot do
    ├── NotFittedError (AttributeError)       retarget() before fit()
    ├── NumericalError (ArithmeticError)      a solve failed or is singular
    ├── FileFormatError (ValueError)          a file is malformed, truncated, unsupported
    │   └── FormatMismatchError               not this format (another kind of file; a reader declines it)
    ├── OutputError (OSError)                 writing refused (would overwrite an input ...)
    ├── ResourceLimitError (MemoryError)      a file would exceed the memory budget
    ├── ConfigError (ValueError)              registry.toml, manifests, settings
    │   └── ParameterError (also InputError)  a method's parameter value is not valid
    └── PluginError                           a plugin failed to load or misbehaved
        ├── PluginLoadError
        ├── DuplicatePluginError
        ├── PluginOutputError
        └── PluginTimeoutError (TimeoutError)  a plugin overran its time limit

Warnings (``warnings.warn``; filter them with ``warnings.simplefilter``)::

    FaceRetargetWarning (UserWarning)
    └── CorrespondenceWarning              a cross-topology correspondence is poor somewhere
"""

from __future__ import annotations

__all__ = [
    "FaceRetargetError",
    "InputError",
    "ShapeError",
    "NonFiniteError",
    "IndexRangeError",
    "DegenerateGeometryError",
    "TopologyMismatchError",
    "CorrespondenceError",
    "UnknownNameError",
    "CapabilityError",
    "NotFittedError",
    "NumericalError",
    "FileFormatError",
    "FormatMismatchError",
    "OutputError",
    "ResourceLimitError",
    "ConfigError",
    "ParameterError",
    "PluginError",
    "PluginLoadError",
    "DuplicatePluginError",
    "PluginOutputError",
    "PluginTimeoutError",
    "FaceRetargetWarning",
    "CorrespondenceWarning",
]


class FaceRetargetError(Exception):
    """Base class of every error faceretarget raises on purpose."""


class InputError(FaceRetargetError, ValueError):
    """An array or model object given to faceretarget is not valid."""


class ShapeError(InputError):
    """An array has the wrong rank, length or trailing dimension."""


class NonFiniteError(InputError):
    """An array holds NaN or infinity where only finite values are allowed."""


class IndexRangeError(InputError, IndexError):
    """Indices (triangle corners, landmark ids, frames) fall outside their range."""


class DegenerateGeometryError(InputError):
    """Geometry a method cannot work with: zero-area or repeated triangles, coincident points."""


class TopologyMismatchError(InputError):
    """Two meshes, frames or rig shapes that must share topology do not."""


class CorrespondenceError(InputError):
    """Two faces of different topology could not be put in correspondence reliably
    (too few matched points, landmarks that do not correspond)."""


class UnknownNameError(FaceRetargetError, KeyError):
    """A name (retargeter, shape, format, metric, case) that is not known.

    The message lists the valid choices.
    """

    def __str__(self) -> str:  # KeyError quotes its message; we want plain text
        return str(self.args[0]) if self.args else ""


class CapabilityError(FaceRetargetError, TypeError):
    """A retargeter was asked for something it cannot do; the message names what is missing."""


class NotFittedError(FaceRetargetError, AttributeError):
    """A retargeter was used before :meth:`fit`."""


class NumericalError(FaceRetargetError, ArithmeticError):
    """A numerical step failed (singular system, no convergence)."""


class FileFormatError(FaceRetargetError, ValueError):
    """A file is malformed, truncated or not of a supported format; the message names the file."""


class FormatMismatchError(FileFormatError):
    """A file is not of the format its reader expects: its content says it is something
    else (a PNG image named ``.c3d``: the message names what it looks like), or a reader
    (a plugin's too) declines it. :func:`faceretarget.io.load` then tries the next reader
    registered for the extension, if any."""


class OutputError(FaceRetargetError, OSError):
    """Writing was refused or failed (it would overwrite an input, the folder is missing ...)."""


class ResourceLimitError(FaceRetargetError, MemoryError):
    """A file declares sizes that would exceed the memory budget (``FACERETARGET_MEMORY_BUDGET``)."""


class ConfigError(FaceRetargetError, ValueError):
    """A configuration file (``registry.toml``, a batch manifest, a mapping file) is malformed."""


class ParameterError(ConfigError, InputError):
    """A method's parameter has a value outside its declared constraints
    (:mod:`faceretarget.validation`); the message names the method, the parameter, the
    valid values and the value given. Both a :class:`ConfigError` and an :class:`InputError`."""


class PluginError(FaceRetargetError):
    """A plugin failed to load or misbehaved; the message names the plugin and its distribution."""


class PluginLoadError(PluginError, ImportError):
    """A plugin's entry point could not be imported or its hooks are invalid."""


class DuplicatePluginError(PluginError):
    """Two plugins registered the same name; the message names both origins."""


class PluginOutputError(PluginError):
    """A plugin returned something invalid (wrong shapes, NaN, wrong types)."""


class PluginTimeoutError(PluginError, TimeoutError):
    """A plugin did not finish importing or running within its time limit
    (``FACERETARGET_TIMEOUT`` / ``--timeout`` per run, ``FACERETARGET_IMPORT_TIMEOUT`` per import)."""


class FaceRetargetWarning(UserWarning):
    """Base class of the warnings faceretarget issues: a result was produced, but part of it
    may be wrong; the message names what and where."""


class CorrespondenceWarning(FaceRetargetWarning):
    """The correspondence between two faces of different topology is poor in some regions
    (flipped triangles, landmarks not reached, target parts the source does not cover); the
    message names the regions. Past the hard limits a :class:`CorrespondenceError` is raised
    instead (thresholds ``CORRESPONDENCE_*`` in :mod:`faceretarget.config`)."""
