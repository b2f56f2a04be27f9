"""The model zoo: trained policies that ship with the project, named `zoo:NAME`.

`zoo/NAME/` holds `checkpoint.pt` (for `mat eval`, `mat finetune`, `mat export`), `onnx/`
(its bundle, for `Policy.load("zoo:NAME")`) and `card.json` (how it was made and what it
scores). The zoo is the `zoo/` directory of a source checkout, or the directory that the
environment variable MAT_ZOO names.
"""

from __future__ import annotations

import os
import re
from pathlib import Path

PREFIX = "zoo:"
NAME = re.compile(r"[A-Za-z0-9][A-Za-z0-9_.-]*")


def zoo_dir() -> Path:
    """Where the zoo's models are: $MAT_ZOO, else `zoo/` beside this package's source."""
    return Path(os.environ.get("MAT_ZOO") or Path(__file__).resolve().parent.parent / "zoo")


def models() -> list[str]:
    """The names of the zoo's models (directories with a card)."""
    root = zoo_dir()
    if not root.is_dir():
        return []
    names = (p.parent.name for p in root.glob("*/card.json"))
    return sorted(name for name in names if NAME.fullmatch(name))  # not `zoo add`'s staging


def locate(path: str | os.PathLike, part: str) -> Path:
    """`path` as given, or for `zoo:NAME` the model's `part` (`checkpoint.pt`, `onnx`);
    `FileNotFoundError` naming the models there are for an unknown name."""
    text = os.fspath(path)
    if not text.startswith(PREFIX):
        return Path(path)
    name = text[len(PREFIX) :]
    if not NAME.fullmatch(name) or ".." in name:
        raise ValueError(f"{text!r}: a zoo name is letters, digits, '.', '_' and '-'")
    model = zoo_dir() / name
    if not (model / "card.json").is_file():
        known = ", ".join(models()) or "none"
        raise FileNotFoundError(f"no zoo model {name!r} in {zoo_dir()}; the zoo has: {known}")
    return model / part
