"""Progress wherever the user is: plain lines in logs and pipes (while the work runs), a bar on a terminal,
tqdm.auto in Jupyter."""

from __future__ import annotations

import io
import os
import re
import subprocess
import sys
import time
import types
from pathlib import Path

from apmgsrn.progress import Progress, progress_mode

VOLUME = Path(__file__).parent / "data" / "reference_neghip_24.npy"
LINE = re.compile(r"^train (\d+)/(\d+) it \(\d+%\)")


def test_a_training_run_piped_to_a_file_shows_progress_lines_while_it_runs(tmp_path):
    iterations = 600
    command = [sys.executable, "-m", "apmgsrn", "train", str(VOLUME), "--out", str(tmp_path / "m.apmgsrn"),
               "--grids", "4", "--resolution", "8", "--width", "16", "--iterations", str(iterations),
               "--batch-size", "1024", "--device", "cpu"]
    env = {**os.environ, "APMGSRN_PROGRESS_SECONDS": "0.3", "OMP_NUM_THREADS": "1"}
    src = str(Path(__file__).resolve().parents[1] / "src")
    env["PYTHONPATH"] = src + os.pathsep + env.get("PYTHONPATH", "")
    process = subprocess.Popen(command, stdout=subprocess.PIPE, stderr=subprocess.PIPE, text=True, env=env)
    seen_while_running = []
    lines = []
    deadline = time.time() + 300
    for line in process.stderr:  # read as the child writes: a pipe is not a terminal
        lines.append(line.rstrip("\n"))
        match = LINE.match(line)
        if match and int(match.group(1)) < iterations and process.poll() is None:
            seen_while_running.append(line)
        assert time.time() < deadline
    stdout = process.stdout.read()
    assert process.wait() == 0, "\n".join(lines)
    assert "PSNR" in stdout and "max abs error" in stdout
    assert seen_while_running, f"no progress line before the run ended: {lines}"
    middle = seen_while_running[0]
    # iteration, loss, PSNR estimate, grid state, rate and time left, on one line
    assert re.search(r"\| loss \S+ \| psnr \S+dB \| grids \S+ \| [\d.]+k? it/s \| \d+:\d\d elapsed, \d+:\d\d left$",
                     middle.rstrip()), middle
    assert LINE.match(lines[-1]) and LINE.match(lines[-1]).group(1) == str(iterations), lines[-1]
    assert "left" not in lines[-1]  # the last line: everything done


def test_plain_lines_report_count_figures_rate_and_time_left(monkeypatch):
    monkeypatch.setenv("APMGSRN_PROGRESS_SECONDS", "0")
    stream = io.StringIO()
    with Progress(200, unit="it", description="train", stream=stream) as progress:
        assert progress.mode == "lines"  # a StringIO is no terminal
        progress.set_fields(loss="1.00e-03")
        time.sleep(0.01)
        progress.update(50)
    lines = stream.getvalue().splitlines()
    assert lines[0].startswith("train 50/200 it (25%) | loss 1.00e-03 | ") and lines[0].endswith(" left")
    assert lines[-1].startswith("train 50/200 it (25%)")  # the closing line


def test_a_failed_run_ends_without_a_closing_line_so_the_error_stays_last(monkeypatch):
    monkeypatch.setenv("APMGSRN_PROGRESS_SECONDS", "3600")
    stream = io.StringIO()
    try:
        with Progress(10, stream=stream) as progress:
            progress.update(3)
            raise RuntimeError("boom")
    except RuntimeError:
        pass
    assert stream.getvalue() == ""


def test_big_counts_are_short_and_a_resumed_run_counts_its_rate_from_where_it_resumed(monkeypatch):
    monkeypatch.setenv("APMGSRN_PROGRESS_SECONDS", "3600")
    progress = Progress(2_000_000, unit="voxel", description="eval", initial=1_000_000, stream=io.StringIO())
    progress.update(500_000)
    line = progress.line()
    assert line.startswith("eval 1.5M/2.0M voxel (75%)")
    rate = float(re.search(r"\| ([\d.]+)([kMG]?) voxel/s", line).group(1))
    assert rate > 0


def test_the_mode_follows_the_stream_and_a_jupyter_kernel(monkeypatch):
    class Terminal(io.StringIO):
        def isatty(self):
            return True

    assert progress_mode(io.StringIO()) == "lines"
    assert progress_mode(Terminal()) == "terminal"
    shell = types.SimpleNamespace(config={"IPKernelApp": {}})
    monkeypatch.setitem(sys.modules, "IPython", types.SimpleNamespace(get_ipython=lambda: shell))
    assert progress_mode(Terminal()) == "notebook"
    shell.config = {}  # a terminal IPython is no notebook
    assert progress_mode(io.StringIO()) == "lines"
    assert Progress(5, enabled=False).mode == "off"
