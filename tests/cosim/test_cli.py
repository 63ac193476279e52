"""The driving commands of the `cosim` CLI, run in-process."""

import imageio.v3 as iio

from eval.cli import main


def test_scenarios_lists_the_five(capsys):
    assert main(["scenarios"]) == 0
    out = capsys.readouterr().out.splitlines()
    assert [line.split()[0] for line in out] == ["env_1", "env_2", "env_3", "env_4", "env_5"]


def test_drive_prints_a_summary_per_ac(capsys):
    assert main(["drive", "env_5", "--agents", "2", "--steps", "50", "--quiet"]) == 0
    out = capsys.readouterr().out
    assert "env_5 (Merge): 2 ACs" in out
    assert "ac_0" in out and "ac_1" in out and "outcome" in out


def test_view_writes_mosaics_and_gifs(tmp_path, capsys):
    code = main(["view", "env_3", "--agents", "3", "--steps", "12", "--moments", "2",
                 "--out", str(tmp_path), "--quiet"])
    assert code == 0
    pngs = sorted(tmp_path.glob("mosaic_*.png"))
    assert len(pngs) == 2
    img = iio.imread(pngs[0])
    assert img.ndim == 3 and img.shape[0] >= 2 * 84 and img.shape[1] > 3 * 2 * 84
    assert iio.imread(tmp_path / "camera_ac_0.gif").shape[0] >= 10  # frames
    assert (tmp_path / "overview.gif").exists()
    assert "wrote:" in capsys.readouterr().out


def test_errors_exit_non_zero_with_a_one_line_reason(capsys):
    assert main(["drive", "env_9", "--quiet"]) == 2  # a user error (docs/reference.md)
    err = capsys.readouterr().err
    assert err.startswith("cosim: error: unknown scenario 'env_9'") and err.count("\n") == 1


def test_nets_check_passes_on_the_committed_build(capsys):
    assert main(["nets", "check"]) == 0
    assert "up to date" in capsys.readouterr().out
