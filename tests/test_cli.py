"""The `mat` command line: tables, one-line errors, non-zero exit codes."""

from click.testing import CliRunner

from mat_sdk.cli import main


def test_envs_table_lists_every_robot():
    result = CliRunner().invoke(main, ["envs"])
    assert result.exit_code == 0, result.output
    for env_id in (
        "cheetah-6x1",
        "quadruped-4x3",
        "humanoid-limbs",
        "swimmer-6",
        "mamujoco:HalfCheetah-6x1",
    ):
        assert env_id in result.output
    assert "episode" in result.output or "limit" in result.output


def test_rollout_runs_a_random_team_with_a_fault():
    result = CliRunner().invoke(
        main, ["rollout", "hopper-2x2", "--steps", "20", "--fault", "knee=zero"]
    )
    assert result.exit_code == 0, result.output
    assert "episode returns" in result.output


def test_user_mistakes_give_one_line_and_exit_code():
    result = CliRunner().invoke(main, ["rollout", "cheetah-9x9"])
    assert result.exit_code != 0
    assert "unknown environment id 'cheetah-9x9'" in result.output
    assert "Traceback" not in result.output
    result = CliRunner().invoke(main, ["rollout", "cheetah-6x1", "--fault", "bfoot"])
    assert result.exit_code != 0 and "NAME=zero or NAME=remove" in result.output
