"""The ``lapwarp`` command line: every subcommand with tiny settings, and clear errors for bad arguments."""

from __future__ import annotations

import json
import re
import shutil
import subprocess

import pytest

from lapwarp import cli


def run_cli(capsys, *argv: str) -> tuple[int, str, str]:
    status = cli.main(list(argv))
    captured = capsys.readouterr()
    return status, captured.out, captured.err


def summary(out: str) -> dict[str, str]:
    """The run summary table as {row label: value}."""
    rows = {}
    for line in out.splitlines():
        match = re.match(r"^(\S.*?)\s{2,}(.*)$", line)
        if match:
            rows[match.group(1)] = match.group(2)
    return rows


def test_list(capsys):
    status, out, _ = run_cli(capsys, "list")
    assert status == 0
    row = next(line for line in out.splitlines() if line.startswith("Reach"))
    assert row.split()[1] == "6"  # STATE observation: end-effector and target positions
    assert "Box(-1, 1, (3,))" in row and "Discrete(7)" in row and "RGB" in row


def test_run_random(capsys, device):
    status, out, err = run_cli(capsys, "run", "Reach", "--num-envs", "3", "--steps", "4", "--device", device,
                               "--no-progress")
    assert status == 0, err
    rows = summary(out)
    assert rows["task"] == "Reach" and rows["policy"] == "random"
    assert rows["env steps"] == "4 x 3 = 12"
    assert float(rows["env-steps/s"].replace(",", "")) > 0
    assert "\r" not in err  # no progress bar when disabled


def test_run_discrete_random_with_progress_bar(capsys, device):
    status, out, err = run_cli(capsys, "run", "Reach", "--num-envs", "2", "--steps", "3", "--device", device,
                               "--set", "action_type=DISCRETE", "--progress")
    assert status == 0, err
    assert "\r[" in err and "3/3 100.0%" in err
    assert summary(out)["env steps"] == "3 x 2 = 6"


def test_run_expert_succeeds(capsys, device):
    status, out, err = run_cli(capsys, "run", "Reach", "--num-envs", "4", "--steps", "150", "--policy", "expert",
                               "--device", device, "--seed", "1")
    assert status == 0, err
    rows = summary(out)
    assert int(rows["episodes finished"]) >= 4
    assert rows["success rate"] == "100.0 %"
    assert float(rows["mean return"]) > 50.0  # the success bonus (100) dominates


def test_run_writes_usd(capsys, device, tmp_path):
    pytest.importorskip("pxr")
    from pxr import Usd

    from lapwarp.usd import validate_usd

    path = tmp_path / "run.usda"
    status, out, err = run_cli(capsys, "run", "Reach", "--num-envs", "6", "--steps", "3", "--device", device,
                               "--usd", str(path))
    assert status == 0, err
    assert "usd" in summary(out)
    assert validate_usd(path) == []
    stage = Usd.Stage.Open(str(path))
    assert [stage.GetPrimAtPath(f"/World/env_{i}").IsValid() for i in range(6)] == [True] * 4 + [False] * 2
    assert stage.GetEndTimeCode() == 3.0  # time codes 0 (after reset) .. 3


def test_interrupted_run_keeps_the_recording(capsys, device, tmp_path, monkeypatch):
    pytest.importorskip("pxr")
    from pxr import Usd

    make_policy = cli._make_policy

    def interrupting_policy(env, name, seed):
        policy, calls = make_policy(env, name, seed), []

        def act(obs):
            calls.append(1)
            if len(calls) == 3:
                raise KeyboardInterrupt  # Ctrl-C during the third step
            return policy(obs)

        return act

    monkeypatch.setattr(cli, "_make_policy", interrupting_policy)
    path = tmp_path / "partial.usda"
    status, _, err = run_cli(capsys, "run", "Reach", "--num-envs", "2", "--steps", "10", "--device", device,
                             "--usd", str(path))
    assert status == 130 and "interrupted" in err and "saved 3 time samples" in err
    assert Usd.Stage.Open(str(path)).GetEndTimeCode() == 2.0  # reset state + 2 completed steps


def test_run_rgb_observations_and_image_grid(capsys, device, tmp_path):
    from lapwarp.imaging import read_png

    path = tmp_path / "grid.png"
    status, out, err = run_cli(capsys, "run", "Reach", "--num-envs", "4", "--steps", "2", "--device", device,
                               "--obs", "rgb", "--image-size", "32", "--save-images", str(path))
    assert status == 0, err
    assert summary(out)["observation"] == "RGB"
    image = read_png(path)
    assert image.shape == (2 * 33 + 1, 2 * 33 + 1, 3)  # 2 x 2 grid of 32-pixel images, 1-pixel padding
    assert image.max() > 100  # something was drawn, not only the dark background


def test_bench(capsys, device, tmp_path):
    out_json = tmp_path / "bench.json"
    status, out, err = run_cli(capsys, "bench", "Reach", "--device", device, "--num-envs", "2", "--seconds", "0.02",
                               "--out", str(out_json))
    assert status == 0, err
    assert "env-steps/s" in out
    report = json.loads(out_json.read_text())
    assert report["results"][0]["task"] == "Reach" and report["results"][0]["num_envs"] == 2


@pytest.mark.parametrize("argv, message", [
    (["run", "Nope", "--steps", "1"], "unknown task 'Nope'"),
    (["bench", "Nope"], "unknown task 'Nope'"),
    (["frobnicate"], "invalid choice: 'frobnicate'"),
    (["run", "Reach", "--set", "sphere_radus=0.01"], "unknown config key(s) ['sphere_radus']"),
    (["run", "Reach", "--set", "observation_type=XRAY"], "observation_type='XRAY' is not valid"),
    (["run", "Reach", "--set", "sphere_radius"], "--set expects KEY=VALUE"),
    (["run", "Reach", "--num-envs", "0"], "expected a positive integer, got 0"),
    (["run", "Reach", "--obs", "thermal"], "invalid choice: 'thermal'"),
    (["run", "Reach", "--save-images", "grid.jpg"], "ending in .png"),
    (["run", "Reach", "--usd", "out.obj"], ".usda, .usd or .usdc"),
    (["bench", "Reach", "--frobnicate"], "unrecognized arguments: --frobnicate"),
    (["run", "Reach", "--usd", "no_such_folder/x.usda"], "does not exist"),
    (["run", "Reach", "--save-images", "no_such_folder/g.png"], "--mkdir creates missing folders"),
    (["run", "Reach", "--set", "sphere_radius=big"], "sphere_radius='big' is invalid"),
    (["run", "Reach", "--set", "clip_actions=maybe"], "clip_actions='maybe' is invalid"),
    (["run", "Reach", "--set", "seed=1.5"], "seed=1.5 is invalid"),
    ([], "usage: lapwarp"),
])
def test_bad_arguments_exit_2_with_a_clear_message(capsys, argv, message):
    status, out, err = run_cli(capsys, *argv)
    assert status == 2
    assert message in err
    assert "Traceback" not in err and out == ""


def test_output_folders_are_created_only_with_mkdir(capsys, device, tmp_path):
    pytest.importorskip("pxr")
    usd, png = tmp_path / "a" / "b" / "run.usda", tmp_path / "c" / "grid.png"
    status, _, err = run_cli(capsys, "run", "Reach", "--num-envs", "2", "--steps", "1", "--device", device,
                             "--usd", str(usd))
    assert status == 2 and "does not exist" in err and not (tmp_path / "a").exists()
    status, out, err = run_cli(capsys, "run", "Reach", "--num-envs", "2", "--steps", "1", "--device", device,
                               "--usd", str(usd), "--save-images", str(png), "--image-size", "16", "--mkdir")
    assert status == 0, err
    rows = summary(out)
    assert rows["usd"].startswith(str(usd)) and rows["images"].startswith(str(png))
    assert usd.is_file() and png.is_file()


def test_run_reports_contact_overflows(capsys, device):
    status, out, err = run_cli(capsys, "run", "DeflectSpheres", "--num-envs", "2", "--steps", "40", "--device", device,
                               "--policy", "expert", "--set", "contact_capacity=1", "--seed", "3")
    assert status == 0, err
    assert "env-steps lost contact records" in summary(out)["contact overflows"]
    status, out, err = run_cli(capsys, "run", "Reach", "--num-envs", "2", "--steps", "1", "--device", device)
    assert "contact overflows" not in summary(out)  # no contact systems, nothing to report


def test_help_and_version_exit_0(capsys):
    status, out, _ = run_cli(capsys, "run", "--help")
    assert status == 0 and "--save-images" in out
    status, out, _ = run_cli(capsys, "--version")
    assert status == 0 and out.startswith("lapwarp ")


def test_console_script():
    exe = shutil.which("lapwarp")
    if exe is None:
        pytest.skip("the lapwarp console script is not installed (pip install -e .)")
    done = subprocess.run([exe, "run", "Nope"], capture_output=True, text=True, timeout=120)
    assert done.returncode == 2
    assert "lapwarp: error: unknown task 'Nope'" in done.stderr and "Traceback" not in done.stderr
