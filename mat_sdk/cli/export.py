"""`mat export`: a checkpoint as an ONNX bundle for the torch-free runtime."""

from __future__ import annotations

from pathlib import Path

import click

from mat_sdk.cli import main
from mat_sdk.cli.common import trust_option, user_errors


@main.command("export")
@click.argument("checkpoint", type=click.Path())
@click.option(
    "-o",
    "--out",
    "out_dir",
    type=click.Path(file_okay=False),
    help="Bundle directory [CHECKPOINT_onnx].",
)
@click.option("--force", is_flag=True, help="Replace an existing bundle directory.")
@click.option(
    "--engine", "engines", multiple=True, type=click.Choice(["openvino"]),
    help="Also run every graph in this engine (CPU, f32) against ONNX Runtime and report "
    "parity and what it refuses (pip install 'mat-sdk[openvino]').",
)  # fmt: skip
@trust_option()
@user_errors
def export_command(
    checkpoint: str, out_dir: str | None, force: bool, engines: tuple[str, ...]
) -> None:  # fmt: skip
    """Export CHECKPOINT to an ONNX bundle for the torch-free runtime.

    \b
    Writes encoder.onnx, decoder_step.onnx (KV-cached single-agent step) and manifest.json,
    after checking ONNX Runtime against torch on 1, 2, 6, 17 and 64 agents; a bundle that
    disagrees by more than 1e-4 is refused and nothing is written.
    Example: mat export runs/cheetah/checkpoint.pt -o cheetah_onnx
    """
    from mat_export import export

    target = (
        Path(out_dir) if out_dir else Path(checkpoint).with_name(Path(checkpoint).stem + "_onnx")
    )
    manifest = export(checkpoint, target, force=force, engines=engines)
    worst = max(manifest["parity"]["max_abs_diff"].values())
    counts = ", ".join(manifest["parity"]["max_abs_diff"])
    graphs = ", ".join(f"{name} (opset {g['opset']})" for name, g in manifest["graphs"].items())
    click.echo(f"{target}: {manifest['algo']} ({manifest['kind']}): {graphs}")
    click.echo(f"ORT vs torch max abs diff {worst:.2e} over agent counts {counts}")
    second = manifest["parity"].get("openvino")
    if second is not None:
        diffs = ", ".join(f"{name} {d:.1e}" for name, d in second["max_abs_diff"].items())
        click.echo(f"{second['engine']} (CPU, f32) vs ORT max abs diff: {diffs}")
        for what, diff in second.get("wrong", {}).items():
            click.echo(f"  {second['engine']} computes {what} wrong: off by {diff:.2g}")
        for what, reason in second["refused"].items():
            click.echo(f"  {second['engine']} refuses {what}: {reason}")
        for name, diff in second["reused"].items():
            click.echo(
                f"  {name}: one compiled model serving another agent count in turn is off by "
                f"{diff:.2g}: compile one per count"
            )
