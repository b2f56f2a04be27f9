"""Env ids and what they build: one lookup for every tool (trainer, eval, export, controller).

An id is, in the order tried:
- one registered in this process (`register`, or an env object given to `Trainer`);
- a built-in robot (`cheetah-6x1`, `swimmer-N`, ...), `mamujoco:<Scenario>-<conf>`,
  `coordination-N`;
- one an installed package registers under the entry-point group `mat_sdk.envs`
  (`[project.entry-points."mat_sdk.envs"] arm-3x2 = "my_robots:arm_3x2"`);
- `module:function` (Gymnasium's convention): the function, called with no arguments,
  returns what `from_dm_control`, `from_mjcf` or `from_pettingzoo` return.
Checkpoints and bundles record the id, so every tool rebuilds the same env from it.

The trust rule: an id read from a file (a checkpoint, a manifest, a zoo card) is data, not
code. A `module:function` id from a file is imported only when the user opts in for that run
(`check_trusted`: the file given as `Trusted(path)`, on the command line with
`--trust-env-code`); built-in, `mamujoco:`, registered and installed ids need no opt-in, since
they run only code that is already installed. Even then, an id must name a plain Python
function outside the standard library, called with no arguments, that returns a spec.
"""

from __future__ import annotations

import importlib
import inspect
import os
import sys
from collections.abc import Callable, Iterable, Mapping
from dataclasses import dataclass
from importlib import metadata
from pathlib import Path
from typing import Any

from mat_sdk.envs.core.games import CoordinationGame
from mat_sdk.envs.core.recipe import TrainingRecipe
from mat_sdk.envs.mujoco.mamujoco import PREFIX as MAMUJOCO
from mat_sdk.envs.mujoco.mamujoco import MaMuJoCoTeam
from mat_sdk.envs.mujoco.robots import FAMILIES, env_ids, spec_for
from mat_sdk.envs.mujoco.sources import RobotSpec
from mat_sdk.envs.mujoco.team import RobotTeam
from mat_sdk.envs.pettingzoo.team import PettingZooSpec, PettingZooTeam

ENTRY_POINT_GROUP = "mat_sdk.envs"
_REGISTERED: dict[str, Any] = {}


@dataclass(frozen=True)
class TeamClassSpec:
    """A built-in family that is a team class of its own (MaMuJoCo, the coordination game)."""

    env_id: str
    kind: type

    def build(self, **options: Any):
        return self.kind(self.env_id, **options)


EnvSpec = RobotSpec | PettingZooSpec | TeamClassSpec
_TEAM_OF = {RobotSpec: RobotTeam, PettingZooSpec: PettingZooTeam}


def register(env_id: str, source: EnvSpec | Callable[[], EnvSpec]) -> str:
    """Make `env_id` name `source` (a spec, or a function returning one) in this process."""
    _REGISTERED[env_id] = source
    return env_id


def id_of(env: str | EnvSpec | Callable[[], EnvSpec]) -> str:
    """The id to record for `env`: an id as given; for a module-level function, its
    `module:function` id (any process can rebuild it); for a spec, its own id, registered
    in this process (other processes cannot rebuild it: give tools a `module:function`)."""
    if isinstance(env, str):
        return env
    if callable(env) and not isinstance(env, EnvSpec):
        module, name = getattr(env, "__module__", None), getattr(env, "__qualname__", "")
        if module and module != "__main__" and name.isidentifier():
            importable = f"{module}:{name}"
            if _imported(importable) is env:
                return importable
        env = _checked(env(), repr(env))
    return register(env.env_id, env)


class UntrustedEnvError(ValueError):
    """An env id read from a file names code to import, and the user has not opted in."""


def imports_code(env_id: str) -> bool:
    """Whether resolving `env_id` would import a module that no installed package declares:
    a `module:function` id that is neither built in, registered nor installed."""
    return (
        isinstance(env_id, str)
        and ":" in env_id
        and env_id not in _REGISTERED
        and not env_id.startswith(MAMUJOCO)
        and not env_id.startswith("coordination-")
        and spec_for(env_id) is None
        and env_id not in _entry_points()
    )


@dataclass(frozen=True)
class Trusted(os.PathLike):
    """A file the user vouches for: a `module:function` env id it records may be imported,
    which runs that module's code. Give it wherever a checkpoint or run path goes
    (`Trainer.load(Trusted("runs/go2/checkpoint.pt"))`); the trust travels with the path, so
    no function between the user and `check_trusted` needs to pass a flag along."""

    path: Path

    def __post_init__(self):
        object.__setattr__(self, "path", Path(self.path))

    def __fspath__(self) -> str:
        return os.fspath(self.path)

    def __str__(self) -> str:
        return str(self.path)


def trusted_as(path: str | os.PathLike, source: str | os.PathLike) -> Path | Trusted:
    """`path` (a copy of `source`, or a file written from it) trusted as `source` is."""
    return Trusted(path) if isinstance(source, Trusted) else Path(path)


def check_trusted(
    env_ids: Iterable[str], source: str | os.PathLike, named: Iterable[str] = ()
) -> None:
    """The one trust decision: refuse the `module:function` ids read from `source` (a file)
    unless the user typed that same id in this process (`named`) or vouched for the file
    (`source` given as `Trusted`). Loading a downloaded file or a tampered run directory must
    never run its code."""
    if isinstance(source, Trusted):
        return
    typed = {id_of(env) for env in named}
    for env_id in env_ids:
        if imports_code(env_id) and env_id not in typed:
            module = str(env_id).partition(":")[0]
            raise UntrustedEnvError(
                f"{source} records the env id {env_id!r}, which would import and run code from "
                f"module {module!r}; an id read from a file runs no code unless you opt in: "
                "pass --trust-env-code (in Python: the path as mat_sdk.envs.Trusted(path)) if "
                "you trust that file, or name the env yourself"
            )


def resolve(env_id: str | EnvSpec) -> EnvSpec:
    """The spec an id names, or ValueError saying what was looked for. A `module:function`
    id is imported here: callers that read the id from a file `check_trusted` it first."""
    if isinstance(env_id, EnvSpec):
        return env_id
    if not isinstance(env_id, str):
        raise ValueError(f"an env is an id string or an env spec, got {env_id!r}")
    if env_id in _REGISTERED:
        return _named(_REGISTERED[env_id], env_id, imported=False)
    robot = spec_for(env_id)
    if robot is not None:
        return robot
    if env_id.startswith(MAMUJOCO):
        return TeamClassSpec(env_id, MaMuJoCoTeam)
    if env_id.startswith("coordination-"):
        return TeamClassSpec(env_id, CoordinationGame)
    installed = _entry_points().get(env_id)
    if installed is not None:
        return _named(installed.load(), env_id)
    if ":" in env_id:
        return _named(_imported(env_id), env_id)
    raise ValueError(
        f"unknown environment id {env_id!r}; valid ids: {', '.join(env_ids())}, "
        f"{', '.join(FAMILIES)}, mamujoco:<Scenario>-<conf>, coordination-N, "
        "module:function (a function returning from_dm_control / from_mjcf / from_pettingzoo), "
        f"or one registered under the entry-point group {ENTRY_POINT_GROUP!r}"
    )


def recipe_of(env: str | EnvSpec) -> TrainingRecipe | None:
    """The training recipe the env's task declares (`from_mjcf(recipe=)`), or None."""
    return getattr(resolve(env), "recipe", None)


# measured best of none / fraction / ends / near-ends / end-flags (docs/TRANSFER.md)
FAMILY_IDENTITY = "end-flags"


def is_family(env: str | EnvSpec) -> bool:
    """Whether an env is a family (one observation size for any agent count), from its spec
    alone; False for an id that names nothing (building it will say why)."""
    try:
        spec = resolve(env)
    except ValueError:
        return False
    if isinstance(spec, RobotSpec):
        return spec.variable_count
    if isinstance(spec, TeamClassSpec) and spec.kind is MaMuJoCoTeam:
        return MaMuJoCoTeam.is_family(spec.env_id)
    return False


def family_identity(env: str | EnvSpec, options: Mapping[str, Any]) -> dict[str, Any]:
    """`options` for a new run: a family gets the count-independent identity that
    transferred best across counts (`FAMILY_IDENTITY`), unless the options name one (None:
    none). A checkpoint records it, so every tool rebuilds the same observations."""
    if "position" in options or not is_family(env):
        return dict(options)
    return {**options, "position": FAMILY_IDENTITY}


def build_team(env: str | EnvSpec, **options: Any):
    """The team an id or spec names, with the options its team class takes."""
    spec = resolve(env)
    kind = spec.kind if isinstance(spec, TeamClassSpec) else _TEAM_OF[type(spec)]
    _check_options(kind, spec.env_id, options)
    return spec.build(**options)


def installed_ids() -> list[str]:
    """Ids that installed packages register under the entry-point group `mat_sdk.envs`."""
    return sorted(_entry_points())


def _entry_points() -> dict[str, metadata.EntryPoint]:
    return {ep.name: ep for ep in metadata.entry_points(group=ENTRY_POINT_GROUP)}


def _imported(env_id: str):
    """The function `module:function` names: a module outside the standard library, and a
    function defined in that module (no attribute walk into what it imports)."""
    module_name, _, attribute = env_id.partition(":")
    if module_name.partition(".")[0] in sys.stdlib_module_names:
        raise ValueError(
            f"env id {env_id!r} names the standard library module {module_name!r}; an env id "
            "names a function of yours that returns from_mjcf / from_dm_control / "
            "from_pettingzoo"
        )
    if not attribute.isidentifier():
        raise ValueError(
            f"env id {env_id!r}: after the colon comes the name of one function defined in "
            f"module {module_name!r} (no dots), got {attribute[:80]!r}"
        )
    try:
        module = importlib.import_module(module_name)
    except ModuleNotFoundError as error:
        if error.name and module_name.startswith(error.name):  # the module itself, not its import
            raise ValueError(
                f"env id {env_id!r}: no module {module_name!r} to import (is it installed, or "
                "its directory on PYTHONPATH? An env given to Trainer as an object is known "
                "only in that process: give tools a module:function id)"
            ) from None
        raise
    if not hasattr(module, attribute):
        raise ValueError(f"env id {env_id!r}: module {module_name!r} has no {attribute!r}")
    target = getattr(module, attribute)
    if not isinstance(target, EnvSpec) and getattr(target, "__module__", None) != module_name:
        raise ValueError(
            f"env id {env_id!r}: {attribute!r} is not defined in module {module_name!r} (it "
            f"comes from {getattr(target, '__module__', None)!r}); name the function where it "
            "is defined"
        )
    return target


def _named(source: Any, env_id: str, imported: bool = True) -> EnvSpec:
    """`source` (a spec, or a function returning one) as the spec of `env_id`; an `imported`
    source must be a plain Python function (not a builtin such as `os.abort`, nor a class)."""
    if imported and not isinstance(source, EnvSpec) and not inspect.isfunction(source):
        raise ValueError(
            f"{env_id} names a {type(source).__name__}, not a Python function; it must name a "
            "function of no arguments that returns what mat_sdk.envs.from_dm_control, from_mjcf "
            "or from_pettingzoo return"
        )
    if callable(source) and not isinstance(source, EnvSpec):
        try:
            inspect.signature(source).bind()
        except TypeError:
            raise ValueError(
                f"{env_id} must name a function of no arguments that returns what "
                "mat_sdk.envs.from_dm_control, from_mjcf or from_pettingzoo return"
            ) from None
        source = source()
    return _checked(source, env_id).renamed(env_id)


def _checked(spec: Any, where: str) -> EnvSpec:
    if not isinstance(spec, RobotSpec | PettingZooSpec):
        raise ValueError(
            f"{where} must give what mat_sdk.envs.from_dm_control, from_mjcf or from_pettingzoo "
            f"return, got {type(spec).__name__}"
        )
    return spec


def _check_options(kind: type, env_id: str, options: Mapping[str, Any]) -> None:
    """Refuse an option the env does not take, naming it and the ones it does."""
    valid = [
        name
        for name, p in inspect.signature(kind.__init__).parameters.items()
        if p.kind is inspect.Parameter.KEYWORD_ONLY
    ]
    unknown = sorted(set(options) - set(valid), key=str)
    if unknown:
        raise ValueError(
            f"unknown env option(s) {unknown} for {env_id}; it takes {', '.join(valid)}"
        )
    annotations = {
        name: p.annotation for name, p in inspect.signature(kind.__init__).parameters.items()
    }
    for name, value in options.items():
        if value is None:
            continue
        kind_of = _OPTION_KINDS.get(str(annotations[name]))
        if kind_of is None:
            continue
        wanted, valid_value = kind_of
        if not valid_value(value):
            raise ValueError(f"env option {name} must be {wanted} or null, got {value!r}")


def _integer(value: Any) -> bool:
    return isinstance(value, int) and not isinstance(value, bool)


# what each option's annotation allows (every option may also be None: the env's default);
# the team checks the range
_OPTION_KINDS: dict[str, tuple[str, Callable[[Any], bool]]] = {
    "int | None": ("an integer", _integer),
    "bool | None": ("true or false", lambda value: isinstance(value, bool)),
    "str | None": ("a string", lambda value: isinstance(value, str)),
}
