"""What a campaign shows while it runs: setup stage lines in order, a ticking compile state, and a time-left
estimate from the chunks after the first (which includes the compile). No chunk is compiled here."""

from __future__ import annotations

import time

import pytest
from tqdm import tqdm

from wbc_jax.campaign.progress import ProgressBar, clock, time_left


def test_time_left_leaves_out_the_compiling_chunk():
    assert time_left([100.0], [True], 5) is None  # only the chunk with the compile: no estimate yet
    assert time_left([100.0, 10.0, 12.0], [True, False, False], 5) == pytest.approx(55.0)
    assert time_left([100.0, 10.0, 90.0, 12.0], [True, False, True, False], 2) == pytest.approx(22.0)  # resumed
    assert time_left([100.0, 10.0], [True, False], 0) == 0.0
    assert clock(None) == "?" and clock(65.4) == "1:05" and clock(3725) == "1:02:05"


def test_time_left_after_the_second_chunk_is_close():
    """Chunks of 10 s after a first one of 240 s (compile included): after the second chunk the estimate is
    within 50 % of what is left, where an average over all chunks would be off by a factor of 12."""
    walls, fresh, n_chunks = [240.0] + [10.0 + (k % 3) for k in range(19)], [True] + [False] * 19, 20
    for done in range(2, n_chunks):
        actual = sum(walls[done:])
        estimate = time_left(walls[:done], fresh[:done], n_chunks - done)
        assert abs(estimate - actual) <= 0.5 * actual, (done, estimate, actual)


def test_bar_ticks_while_compiling_then_shows_time_left():
    bar = ProgressBar(3, 0, 1.0, 8, 0.001, tick_s=0.02)
    bar.compiling("compiling, then chunk 1")
    time.sleep(0.1)
    ticking = tqdm.format_meter(**bar._bar.format_dict)
    assert "compiling, then chunk 1: 0:00" in ticking, ticking
    bar.chunk_done(100.0, fresh=True)
    assert bar._ticker is None
    assert "? left" in tqdm.format_meter(**bar._bar.format_dict)
    bar.chunk_done(10.0)
    text = tqdm.format_meter(**bar._bar.format_dict)
    bar.close()
    assert "0:10 left" in text and "8 runs" in text, text


def test_stage_lines_in_order(tmp_path, monkeypatch, capsys):
    """``wbc-jax campaign`` prints its stages as they start; a build that fails after them stops the run."""
    from wbc_jax import cli
    from wbc_jax.campaign import runner
    from wbc_jax.errors import SpecError

    def stop(spec, gains=None):
        raise SpecError("stopped after the stage lines")

    monkeypatch.setattr(runner, "build", stop)
    rc = cli.main(["campaign", "--spec", "sweeps/quick.toml", "--out", str(tmp_path / "c"), "--no-report"])
    captured = capsys.readouterr()
    assert rc == 2 and "stopped after the stage lines" in captured.err
    lines = captured.out.splitlines()
    assert lines[0] == "loading JAX, MuJoCo MJX and the controllers...", lines
    assert lines[1].startswith("reading the spec sweeps/quick.toml"), lines
    assert any(line.startswith("building 54 runs on scene flat") for line in lines[2:]), lines


def test_a_bad_spec_fails_before_jax_loads(tmp_path, capsys):
    """``wbc-jax campaign`` and ``warmup`` read the spec before they load JAX and MJX: a bad key is one line on
    stderr, exit 2, no stage line printed and nothing written."""
    from wbc_jax import cli
    from wbc_jax.campaign.spec import SWEEPS

    spec = tmp_path / "bad.toml"
    spec.write_text((SWEEPS / "quick.toml").read_text().replace("[campaign]", "[campaign]\nrepz = 3", 1))
    rc = cli.main(["campaign", "--spec", str(spec), "--out", str(tmp_path / "c")])
    captured = capsys.readouterr()
    assert rc == 2 and "repz" in captured.err and len(captured.err.strip().splitlines()) == 1
    assert "loading JAX" not in captured.out and not (tmp_path / "c").exists()
    assert cli.main(["warmup", "--spec", str(spec)]) == 2  # warmup too, before it builds anything
    captured = capsys.readouterr()
    assert "repz" in captured.err and "building" not in captured.out
