"""The runtime's exceptions: one base class to catch, standard bases for the usual handlers."""

from __future__ import annotations


class MatRuntimeError(Exception):
    """Base class of every error `mat_runtime` raises on purpose."""


class BundleError(MatRuntimeError, OSError):
    """The bundle cannot be used: a missing or altered file, or a format this runtime does not
    read. Nothing was loaded; re-export the checkpoint (`mat export`) or fix the path."""


class InputError(MatRuntimeError, ValueError):
    """`Policy.act` was called with input it cannot act on; the policy is unchanged and keeps
    serving."""
