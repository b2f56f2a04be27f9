"""Where a bundle may be written: refuse, before any work, a target whose contents would be
lost, and stage the new bundle beside it."""

from __future__ import annotations

import json
import tempfile
from pathlib import Path

from mat_export.errors import ExportError
from mat_export.manifest import FORMAT
from mat_runtime.manifest import GRAPH_NAME


def check_target(out_dir: Path, force: bool, checkpoint_path: Path) -> None:
    """Refuse, before any work, to write where it would lose something: over anything but a
    bundle, over a bundle unless `force`, over a bundle that also holds other files (notes,
    the checkpoint itself), or through a symlink."""
    if out_dir.is_symlink():
        raise ExportError(
            f"{out_dir} is a symlink; not replacing it or what it points to; "
            "choose a real directory for the bundle"
        )
    if out_dir.exists() and not out_dir.is_dir():
        raise ExportError(f"{out_dir} is a file; choose a directory for the bundle")
    source = Path(checkpoint_path).resolve()
    if out_dir.exists() and source.is_relative_to(out_dir.resolve()):
        raise ExportError(
            f"{out_dir} holds the checkpoint being exported ({checkpoint_path}); "
            "choose another directory for the bundle"
        )
    if not out_dir.exists() or not any(out_dir.iterdir()):
        return
    manifest = out_dir / "manifest.json"
    try:
        listed = json.loads(manifest.read_text())
        is_bundle = listed.get("format") == FORMAT
        # only the files an exporter writes: a doctored manifest cannot list others as its own
        own = {"manifest.json", *(g for g in listed.get("graphs", {}) if GRAPH_NAME.fullmatch(g))}
    except (OSError, ValueError, AttributeError, TypeError):
        is_bundle, own = False, set()
    if not is_bundle:
        raise ExportError(
            f"{out_dir} exists and is not a MAT bundle (no {FORMAT} manifest.json); "
            "not replacing it, even with --force; choose a new directory"
        )
    foreign = sorted(p.name for p in out_dir.iterdir() if p.name not in own)
    if foreign:
        raise ExportError(
            f"{out_dir} holds files that are not the bundle's ({', '.join(foreign[:5])}"
            f"{', ...' if len(foreign) > 5 else ''}); not replacing it, even with --force; "
            "move them out or choose a new directory"
        )
    if not force:
        raise ExportError(f"{out_dir} exists; pass --force (force=True) to replace it")


def staging(out_dir: Path) -> Path:
    """The empty directory beside `out_dir` that the bundle is built in."""
    try:
        out_dir.parent.mkdir(parents=True, exist_ok=True)
        return Path(tempfile.mkdtemp(prefix=f".{out_dir.name}.", dir=out_dir.parent))
    except OSError as error:
        raise ExportError(
            f"cannot write the bundle {out_dir} ({error.strerror or error}: "
            f"{error.filename or out_dir.parent}); choose a directory you can write to"
        ) from None
