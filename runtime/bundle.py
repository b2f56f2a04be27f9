"""Read and verify a `mat export` bundle: the manifest against its schema first, then every
graph's sha256."""

from __future__ import annotations

import hashlib
import json
import time
from collections.abc import Callable
from dataclasses import dataclass
from pathlib import Path
from typing import Any

from mat_runtime.errors import BundleError
from mat_runtime.manifest import check_manifest
from mat_runtime.zoo import locate

FORMAT = "mat-onnx"
SUPPORTED_VERSIONS = (1,)


@dataclass(frozen=True)
class Bundle:
    """A verified bundle: its manifest and each graph's bytes (loaded exactly as hashed)."""

    path: Path
    manifest: dict[str, Any]
    graphs: dict[str, bytes]


class _Changed(BundleError):
    """A file vanished or its hash changed while it was read: perhaps `mat export --force`
    replaced the bundle meanwhile."""


TRIES = 3  # reads of a bundle that changes under the reader


def read_bundle(path: str | Path, select: Callable[[dict], list[str]]) -> Bundle:
    """The manifest, checked, and the graphs `select(manifest)` names, each checked by sha256.
    `path` may name a zoo model: `zoo:NAME`. A bundle replaced while it is read (`mat export
    --force`) is read again, up to `TRIES` times."""
    try:
        path = locate(path, "onnx")
    except (ValueError, FileNotFoundError) as error:
        raise BundleError(str(error)) from None
    for attempt in range(1, TRIES + 1):
        try:
            return _read(path, select)
        except _Changed:
            if attempt == TRIES:
                raise
            time.sleep(0.01 * attempt)


def _read(path: Path, select: Callable[[dict], list[str]]) -> Bundle:
    manifest_path = path / "manifest.json"
    if path.is_file():
        hint = (
            f"pass its directory, {path.parent}"
            if path.name == "manifest.json"
            else "pass the directory `mat export` wrote (a checkpoint needs `mat export` first)"
        )
        raise BundleError(f"{path}: a file, not a bundle directory; {hint}")
    if not path.is_dir():
        raise BundleError(f"{path}: no such bundle directory; create one with `mat export`")
    if not manifest_path.is_file():
        raise BundleError(f"{path}: no manifest.json; is this a `mat export` bundle?")
    try:
        manifest = json.loads(manifest_path.read_text())
    except FileNotFoundError:
        raise _Changed(f"{manifest_path}: vanished while it was read") from None
    except (json.JSONDecodeError, UnicodeDecodeError) as err:
        raise BundleError(
            f"{manifest_path}: not valid JSON ({err}); re-export the bundle"
        ) from None
    except RecursionError:
        raise BundleError(f"{manifest_path}: nested too deeply; re-export the bundle") from None
    if not isinstance(manifest, dict) or manifest.get("format") != FORMAT:
        raise BundleError(f"{manifest_path}: format is not {FORMAT!r}; is this a MAT bundle?")
    version = manifest.get("version")
    if (
        isinstance(version, bool)
        or not isinstance(version, int)
        or version not in SUPPORTED_VERSIONS
    ):
        raise BundleError(
            f"{manifest_path}: bundle format version {version!r}, this runtime reads "
            f"{', '.join(map(str, SUPPORTED_VERSIONS))}; upgrade mat-sdk or re-export with this one"
        )
    check_manifest(manifest, str(manifest_path))
    directory = path.resolve()
    graphs = {}
    for name in select(manifest):
        entry = manifest["graphs"].get(name)
        if entry is None:
            raise BundleError(f"{manifest_path}: lists no {name}; re-export the bundle")
        file = path / name
        if not file.is_file():
            raise _Changed(f"{file}: missing; the bundle is incomplete, re-export it")
        if file.resolve().parent != directory:  # a symlink out of the bundle
            raise BundleError(
                f"{file}: resolves outside the bundle directory ({file.resolve()}); "
                "a bundle's graphs must be its own files"
            )
        try:
            data = file.read_bytes()
        except FileNotFoundError:
            raise _Changed(f"{file}: vanished while it was read") from None
        if hashlib.sha256(data).hexdigest() != entry.get("sha256"):
            raise _Changed(
                f"{file}: sha256 does not match the manifest (corrupt or modified); re-export it"
            )
        graphs[name] = data
    return Bundle(path, manifest, graphs)
