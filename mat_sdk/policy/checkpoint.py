"""The checkpoint file: one `torch.save` of plain containers, written atomically.

`{"format": "mat-checkpoint", "version": 1, "config", "model", "optimizer", "progress",
"rng", "obs_norm", "value_norm", "envs"}`. Loaded with `weights_only=True`: a checkpoint can
hold no code.
"""

from __future__ import annotations

import errno
import os
import re
import shutil
import tempfile
import warnings
from dataclasses import asdict, dataclass
from pathlib import Path
from typing import Any

import numpy as np
import torch

from mat_runtime import zoo
from mat_sdk.common import files
from mat_sdk.envs.core.checks import is_real, short
from mat_sdk.envs.core.faults import as_mapping
from mat_sdk.policy.config import RESUMABLE, TrainConfig

FORMAT = "mat-checkpoint"
VERSION = 1
CHECKPOINT_NAME = "checkpoint.pt"  # a run directory's checkpoint
ZIP_MAGIC = b"PK\x03\x04"  # torch.save writes a zip archive
NORMALISERS = {
    "obs_norm": ("mean", "var"),
    "value_norm": ("running_mean", "running_mean_sq", "debiasing_term"),
}


class CheckpointError(ValueError):
    """The file is missing, not a MAT checkpoint, or of a version this SDK cannot read."""


@dataclass
class Progress:
    """How far a run has gone: env steps taken and updates made (a checkpoint's `progress`)."""

    steps: int = 0
    updates: int = 0


def training_payload(
    config, model_config, policy, optimizer_state, progress, collectors, value_norm
) -> dict[str, Any]:
    """A training run as plain containers and tensors, what `restore_training` puts back: its
    `TrainConfig` and `ModelConfig`, the policy, the optimizer's per-parameter state,
    progress, the rollout collectors (one per env id; the first's normaliser and generators
    are shared) and the value normaliser."""
    collector = collectors[0]
    env = collector.env
    return {
        "config": {
            "train": config.to_dict(),  # the env id is `train.env.id`: stored once
            "model": model_config.to_dict(),
            "env": {
                "counts": [c.env.n_agents for c in collectors],  # per env id
                "agents": list(env.agents),
                "obs_dim": env.obs_dim,
                "action_type": env.action_type,
                "action_dim": env.action_size,
                "act_dim": env.action_width,
                "action_low": -1.0,
                "action_high": 1.0,
                # the domain randomization trained under (the env option's or the env's own)
                "randomization": (
                    env.randomization.to_dict() if getattr(env, "randomization", None) else None
                ),
            },
        },
        "model": {k: v.cpu() for k, v in policy.state_dict().items()},
        "optimizer": optimizer_state,
        "progress": asdict(progress),
        "rng": {
            "torch": collector.generator.get_state().cpu(),
            "shuffle": collector.shuffle_generator.get_state(),
            "device": collector.device.type,  # which kind of generator "torch" is
        },
        "obs_norm": collector.obs_norm.state_dict(),
        "value_norm": value_norm.state_dict(),
        "envs": to_tensors(env.get_state()),
        "next_obs": torch.from_numpy(collector.next_obs.copy()),
        # the envs of `more_envs` (other agent counts), in their order
        "more_envs": [
            {"envs": to_tensors(c.env.get_state()), "next_obs": torch.from_numpy(c.next_obs.copy())}
            for c in collectors[1:]
        ],
    }


def env_id(payload: dict[str, Any]) -> Any:
    """The id of the env a checkpoint trained on (`config.train.env.id`; `config.train.env`
    in files from before the config's parts), unchecked."""
    env = payload["config"]["train"].get("env")
    return env.get("id") if isinstance(env, dict) else env


def recorded_config(payload: dict[str, Any]) -> TrainConfig:
    """The `TrainConfig` a checkpoint records (`TrainConfig.from_dict`)."""
    return TrainConfig.from_dict(payload["config"]["train"])


def recorded_training(payload: dict[str, Any]) -> dict[str, Any]:
    """The training options a checkpoint records, by their flat names."""
    return recorded_config(payload).options()


def pretrained_options(
    payload: dict[str, Any], path: str | os.PathLike, changes: dict[str, Any]
) -> dict[str, Any]:
    """The training options of a fine-tuning run from the checkpoint at `path`: its own, its
    model's size, on one env id, `changes` (faults, lr, any option) over them."""
    train = recorded_training(payload)
    model = payload["config"]["model"]
    train.update({key: model[key] for key in ("n_embd", "n_head", "n_block")})
    train["attention_window"] = model.get("attention_window")  # absent before windows
    return {**train, "init_from": str(path), "more_envs": (), "faults": (), **changes}


def training_options(
    payload: dict[str, Any], path: str | os.PathLike, given: dict[str, Any]
) -> tuple[dict[str, Any], dict[str, Any]]:
    """The training options of the run a checkpoint holds, and what of `given` changes
    them: how to run it (`config.RESUMABLE`); any other option given must be the checkpoint's
    own, since the task, model and hyperparameters are the run's. The one resume rule, for
    `Trainer.load` and `mat train --resume` alike. -> (options, the overrides applied)."""
    train = recorded_training(payload)
    unknown = sorted(set(given) - set(train))
    if unknown:
        raise ValueError(f"{unknown[0]} is not a training option")
    # each given value as the config holds it (a list of ids as a tuple, faults typed, ...)
    given = {k: v for k, v in TrainConfig.from_options({**train, **given}).options().items()
             if k in given}  # fmt: skip
    changed = {}
    for field, value in given.items():
        if field in RESUMABLE:
            if value != train.get(field):
                changed[field] = value
        elif value != train[field]:
            was, got = _shown(field, train[field]), _shown(field, value)
            raise ValueError(
                f"{path} continues its run as it was trained, with {field}={was}; got "
                f"{field}={got}. Drop that option, or start a new run in another directory"
            )
    return {**train, **changed}, changed


def _shown(field: str, value: Any) -> str:
    """An option's value as the user gives it: faults in their mapping form, lists."""
    if field == "faults":
        return repr(as_mapping(value))
    return repr(list(value) if isinstance(value, tuple) else value)


def restore_pretrained(
    payload: dict[str, Any], path, *, policy, obs_norm, value_norm, params=None, optimizer=None,
    lr: float | None = None,
) -> None:  # fmt: skip
    """A pre-trained policy into a new run (few-shot): its weights and both normalisers, and
    given `params` and `optimizer`, its Adam moments too (at the new run's `lr`)."""
    load_weights(policy, payload["model"], path)
    obs_norm.load_state_dict(payload["obs_norm"])
    value_norm.load_state_dict(payload["value_norm"])
    if optimizer is not None:
        optimizer.load_state_dict(params.flat_state(payload["optimizer"]))
        groups = optimizer.param_groups  # a critic with its own rate is the last group
        for group in groups if len(groups) == 1 else groups[:-1]:
            group["lr"] = lr


def restore_training(
    payload: dict[str, Any], path, *, policy, params, optimizer, collectors, value_norm, seed: int
) -> Progress:
    """Put a `training_payload` back into a run built from its config (its policy, flat
    parameters and optimizer, collectors and value normaliser); -> its progress. Or raise
    `CheckpointError` saying the file at `path` cannot be resumed from."""
    try:
        return _restore(payload, policy, params, optimizer, collectors, value_norm, seed)
    except CheckpointError:
        raise
    except (KeyError, TypeError, ValueError, RuntimeError, AttributeError) as error:
        raise CheckpointError(
            f"{path}: cannot resume from it, its training state is incomplete or damaged "
            f"({type(error).__name__}: {error})"
        ) from None


def _restore(payload, policy, params, optimizer, collectors, value_norm, seed) -> Progress:
    collector = collectors[0]
    load_weights(policy, payload["model"], "the checkpoint")
    collector.obs_norm.load_state_dict(payload["obs_norm"])
    value_norm.load_state_dict(payload["value_norm"])
    optimizer.load_state_dict(params.flat_state(payload["optimizer"]))
    for group in optimizer.param_groups:  # an adaptive rate is the file's own: bound it
        lr = group["lr"]
        if not (is_real(lr) and 0 < lr <= 1):
            raise ValueError(f"the optimizer's learning rate must be in (0, 1], got {short(lr)}")
    progress = Progress(int(payload["progress"]["steps"]), int(payload["progress"]["updates"]))
    saved_on = payload["rng"].get("device", "cpu")  # older checkpoints: cpu only
    if saved_on == collector.device.type:
        collector.generator.set_state(payload["rng"]["torch"])
    else:  # CPU and CUDA generators differ: exact resume needs the same device type
        warnings.warn(
            f"the checkpoint's sampling generator is a {saved_on} one and this run is on "
            f"{collector.device.type}: sampling is reseeded, so the run goes on but not "
            "exactly as it would have on the same device",
            stacklevel=4,
        )
        collector.generator.manual_seed(seed + progress.updates)
    collector.shuffle_generator.set_state(payload["rng"]["shuffle"])
    more = payload.get("more_envs", [])  # older checkpoints: one env only
    saved = [{"envs": payload["envs"], "next_obs": payload["next_obs"]}, *more]
    if len(saved) != len(collectors):
        raise CheckpointError(
            f"the checkpoint holds the states of {len(saved)} env ids, the run trains on "
            f"{len(collectors)}"
        )
    for own, state in zip(collectors, saved, strict=True):
        own.env.set_state(to_arrays(state["envs"]))
        own.next_obs = state["next_obs"].numpy().copy()
    return progress


def to_tensors(value: Any) -> Any:
    """numpy inside env states -> tensors, so the checkpoint loads with weights_only=True."""
    if isinstance(value, np.ndarray):
        return torch.from_numpy(value.copy())
    if isinstance(value, dict):
        return {k: to_tensors(v) for k, v in value.items()}
    if isinstance(value, list | tuple):
        return type(value)(to_tensors(v) for v in value)
    return value


def to_arrays(value: Any) -> Any:
    """`to_tensors` undone."""
    if isinstance(value, torch.Tensor):
        return value.numpy()
    if isinstance(value, dict):
        return {k: to_arrays(v) for k, v in value.items()}
    if isinstance(value, list | tuple):
        return type(value)(to_arrays(v) for v in value)
    return value


def save_atomic(payload: dict[str, Any], path: str | os.PathLike) -> Path:
    """Write to a temporary file beside `path`, fsync, then rename over it.

    A crash at any moment leaves either the old checkpoint or the new one, never a torn file;
    so does a full disk, reported as `files.WriteFailed` naming the path.
    """
    path = Path(path)
    with files.writing(path):
        path.parent.mkdir(parents=True, exist_ok=True)
        fd, tmp = tempfile.mkstemp(prefix=f".{path.name}.", suffix=".tmp", dir=path.parent)
    try:
        umask = os.umask(0)
        os.umask(umask)
        os.chmod(tmp, 0o666 & ~umask)  # mkstemp makes 0600; a checkpoint is an ordinary file
        with files.writing(path), os.fdopen(fd, "wb") as handle:
            try:
                torch.save({"format": FORMAT, "version": VERSION, **payload}, handle)
            except RuntimeError as error:  # torch's zip writer reports a failed write so
                raise OSError(_write_errno(path), str(error)) from None
            handle.flush()
            os.fsync(handle.fileno())
        os.replace(tmp, path)
    except BaseException:
        Path(tmp).unlink(missing_ok=True)
        raise
    directory = os.open(path.parent, os.O_RDONLY)
    try:
        os.fsync(directory)
    finally:
        os.close(directory)
    return path


def _write_errno(path: Path) -> int | None:
    """Why torch's writer may have failed: no space left, when the disk is (nearly) full."""
    free = shutil.disk_usage(path.parent).free
    return errno.ENOSPC if free < 1 << 20 else None


def remove_stale_temp_files(directory: str | os.PathLike) -> None:
    """Temp files a killed writer left behind; call when a run (the only writer) starts."""
    for stale in Path(directory).glob(".*.pt.*.tmp"):
        stale.unlink(missing_ok=True)


def locate(path: str | os.PathLike) -> Path:
    """The checkpoint file `path` names: itself, or a zoo model's (`zoo:NAME`)."""
    try:
        return zoo.locate(path, "checkpoint.pt")
    except (ValueError, FileNotFoundError) as error:
        raise CheckpointError(str(error)) from None


def load(path: str | os.PathLike, map_location: str = "cpu") -> dict[str, Any]:
    """Load and validate a checkpoint (a path, or `zoo:NAME`); raises `CheckpointError` with
    what is wrong."""
    path = locate(path)
    if path.is_dir():
        raise CheckpointError(f"{path} is a directory, not a checkpoint; {_directory_hint(path)}")
    if not path.is_file():
        raise CheckpointError(f"no checkpoint at {path}")
    with path.open("rb") as file:
        if file.read(4) != ZIP_MAGIC:
            raise CheckpointError(
                f"{path} is not a MAT checkpoint (not a torch file: pass the checkpoint.pt "
                "that `mat train` wrote)"
            )
    try:
        payload = torch.load(path, map_location=map_location, weights_only=True)
    except Exception as error:
        raise CheckpointError(
            f"{path} is not a MAT checkpoint (a weights-only torch.load refused it: "
            f"{_refusal(error)})"
        ) from None
    if not isinstance(payload, dict) or payload.get("format") != FORMAT:
        raise CheckpointError(f"{path} is not a MAT checkpoint (no 'format': '{FORMAT}' field)")
    version = payload.get("version")
    if isinstance(version, bool) or not isinstance(version, int) or version < 1:
        raise CheckpointError(f"{path}: version must be an integer >= 1, got {version!r}")
    if version > VERSION:
        raise CheckpointError(
            f"{path} has checkpoint version {version}, newer than this SDK reads "
            f"({VERSION}); upgrade mat-sdk"
        )
    _check_structure(path, payload)
    return payload


def _check_structure(path: Path, payload: dict[str, Any]) -> None:
    """The parts every reader uses: config (train, model, env), weights and progress."""
    from mat_sdk.policy.model import ModelConfig

    def fail(field: str, problem: str) -> None:
        raise CheckpointError(f"{path}: {field} {problem}; is the file damaged or edited?")

    config = payload.get("config")
    if not isinstance(config, dict):
        fail("config", f"must be a mapping, got {type(config).__name__}")
    for part in ("train", "model", "env"):
        if not isinstance(config.get(part), dict):
            fail(f"config.{part}", f"must be a mapping, got {type(config.get(part)).__name__}")
    try:
        ModelConfig.from_dict(config["model"])
    except ValueError as error:
        fail("config.model", f"is invalid ({error})")
    trained_on = env_id(payload)
    if not isinstance(trained_on, str):
        fail("config.train.env.id", f"must be a string, got {trained_on!r}")
    if (
        "id" in config["env"] and config["env"]["id"] != trained_on
    ):  # older checkpoints name it twice
        fail("config.env.id", f"differs from config.train.env ({trained_on!r})")
    try:
        recorded_config(payload)
    except (ValueError, TypeError) as error:
        fail("config.train", f"is invalid ({error})")
    weights = payload.get("model")
    if not isinstance(weights, dict) or not all(
        isinstance(k, str) and isinstance(v, torch.Tensor) for k, v in weights.items()
    ):
        fail("model", "must map parameter names to tensors")
    for part, tensors in NORMALISERS.items():
        state = payload.get(part)
        if not isinstance(state, dict) or not all(
            isinstance(state.get(k), torch.Tensor) for k in tensors
        ):
            fail(part, f"must hold the tensors {', '.join(tensors)}")
    progress = payload.get("progress")
    if not isinstance(progress, dict) or not all(
        isinstance(progress.get(k), int) and progress[k] >= 0 for k in ("steps", "updates")
    ):
        fail("progress", f"must hold steps and updates counts, got {progress!r}")


def restore_policy(payload: dict[str, Any], path: str | os.PathLike):
    """The policy a checkpoint holds, in eval mode, and the observation normaliser it was
    trained with (None when it trained on raw observations): what every reader acts with."""
    from mat_sdk.policy.model import ModelConfig, build_policy
    from mat_sdk.policy.normalization import RunningMeanStd

    policy = build_policy(ModelConfig.from_dict(payload["config"]["model"]))
    load_weights(policy, payload["model"], path)
    policy.eval()
    norm = None
    if recorded_config(payload).ppo.normalize_obs:
        norm = RunningMeanStd(policy.cfg.obs_dim)
        norm.load_state_dict(payload["obs_norm"])
    return policy, norm


def load_weights(module: torch.nn.Module, state: dict[str, Any], path: str | os.PathLike) -> None:
    """`module.load_state_dict(state)`, or `CheckpointError` if the weights do not fit it."""
    try:
        module.load_state_dict(state)
    except (RuntimeError, KeyError, TypeError, ValueError) as error:
        first = (str(error).splitlines() or [type(error).__name__])[0]
        raise CheckpointError(
            f"{path}: its weights do not fit the model its config describes ({first})"
        ) from None


def _refusal(error: Exception) -> str:
    """The specific reason in torch's long unpickling message, e.g. "unsupported GLOBAL
    posix.system whose module posix is blocked". Its advice to drop weights_only would let
    the file run code, so it is never passed on."""
    text = str(error)
    for pattern in (
        r"(?:Trying to load |WeightsUnpickler error:\s*)(.+?)(?:\.\s|\.?\n|\.?$)",
        r"(Unsupported (?:global|operand|class)[^\n]*?)(?:\.\s|\.?\n|\.?$)",
    ):
        found = re.search(pattern, text, re.IGNORECASE)
        if found:
            return found.group(1).strip()
    lines = [line for line in text.splitlines() if line.strip() and "weights_only" not in line]
    return lines[0] if lines else type(error).__name__


def _directory_hint(directory: Path) -> str:
    """What the user probably meant by a directory: a run's checkpoint, or a bundle's source."""
    if (directory / CHECKPOINT_NAME).is_file():
        return f"pass the run's checkpoint, {directory / CHECKPOINT_NAME}"
    if (directory / "manifest.json").is_file():
        return (
            "it is an ONNX bundle (load it with mat_runtime.Policy); pass the checkpoint it was "
            "exported from"
        )
    return f"pass the {CHECKPOINT_NAME} that `mat train` wrote"
