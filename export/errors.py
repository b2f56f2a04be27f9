"""The exporter's one error."""


class ExportError(ValueError):
    """The export was refused or failed; nothing was written."""
