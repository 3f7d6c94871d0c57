"""Hostile command lines: outputs onto inputs, sizes out of range, tampered checkpoints, other data on resume.

Each probe of issue 11 (items 3, 4, 8 and 9) is reproduced on a small real volume and answered with one line
``error: ...`` and exit code 2; what was there before is left as it was.
"""

from __future__ import annotations

import hashlib
import json
import math
import os
import shutil
import signal
from pathlib import Path

import numpy as np
import pytest
import torch
from safetensors import safe_open
from safetensors.torch import load_file

import apmgsrn
from apmgsrn.bench.compress import CompressPlan
from apmgsrn.bench.datasets import DataSpec
from apmgsrn.bench.quality import QualityPlan
from apmgsrn.cli.main import main
from apmgsrn.data import check_finite, open_volume
from apmgsrn.data.fingerprint import volume_fingerprint
from apmgsrn.decomposition.coordinator import train_bricks
from apmgsrn.decomposition.executor import ExecutorConfig, open_job_queue
from apmgsrn.decomposition.planner import DecompositionConfig
from apmgsrn.errors import ApmgsrnError, InvalidArgument
from apmgsrn.inference.query import query
from apmgsrn.io import SourceInfo, save_field
from apmgsrn.io.container import sealed_file_bytes
from apmgsrn.models.registry import preset_config
from apmgsrn.models.value_transform import fit_value_transform
from apmgsrn.rendering import Camera, RendererConfig
from apmgsrn.training import fit as fit_module
from apmgsrn.training.trainer import TrainConfig, TrainingCallback

pytestmark = pytest.mark.usefixtures("one_thread")

VOLUME = "neghip_32x32x32_uint8.npy"
#: A few iterations of a tiny model: every probe here is refused before or right after training starts.
FAST = ["--grids", "2", "--resolution", "4", "--iterations", "4", "--batch-size", "512", "--device", "cpu"]


def one_line_error(capsys, *needles: str) -> str:
    """The error: one line ``error: ...`` last on stderr (progress lines may precede it), no traceback, no
    usage block; every needle in it."""
    err = capsys.readouterr().err
    last = err.rstrip("\n").splitlines()[-1]
    assert last.startswith("error: ") and err.count("error: ") == 1, err
    assert "Traceback" not in err and "usage:" not in err, err
    for needle in needles:
        assert needle in last, err
    return last


def digest(path: Path) -> str:
    """SHA-256 of a file, or of every file under a folder (names included)."""
    h = hashlib.sha256()
    files = sorted(p for p in Path(path).rglob("*") if p.is_file()) if Path(path).is_dir() else [Path(path)]
    for file in files:
        h.update(str(file.relative_to(path) if Path(path).is_dir() else "").encode())
        h.update(file.read_bytes())
    return h.hexdigest()


@pytest.fixture(scope="module")
def work(tmp_path_factory, test_data) -> Path:
    """A folder with a real volume ``v.npy`` (neghip 32^3, uint8) and a model ``m.apmgsrn`` trained on it."""
    folder = tmp_path_factory.mktemp("hostile_cli")
    shutil.copy(test_data / VOLUME, folder / "v.npy")
    assert main(["train", str(folder / "v.npy"), "--out", str(folder / "m.apmgsrn"), *FAST]) == 0
    return folder


# ------------------------------------------------------------------------------------------ item 3
def _probe_case(name: str, work: Path, tmp: Path, test_data: Path) -> tuple[list[str], Path]:
    """A command line that names one of its inputs as an output, and that input."""
    v, m = work / "v.npy", work / "m.apmgsrn"
    if name == "train onto its volume":
        return ["train", str(v), "--out", str(v), *FAST], v
    if name == "train through a .. path":
        return ["train", str(v), "--out", str(work / ".." / work.name / "v.npy"), *FAST], v
    if name == "train onto a symbolic link to its volume":
        (tmp / "link.npy").symlink_to(v)
        return ["train", str(v), "--out", str(tmp / "link.npy"), *FAST], v
    if name == "train onto a hard link to its volume":
        os.link(v, tmp / "hard.npy")
        return ["train", str(v), "--out", str(tmp / "hard.npy"), *FAST], v
    if name == "train whose checkpoint is its volume":
        shutil.copy(v, tmp / "w.ckpt")
        return ["train", str(tmp / "w.ckpt"), "--out", str(tmp / "w"), *FAST], tmp / "w.ckpt"
    if name == "train bricks onto its volume":
        return ["train", str(v), "--out", str(v), "--bricks", "2,1,1", *FAST], v
    if name == "decode onto its model":
        shutil.copy(m, tmp / "m.npy")
        return ["decode", str(tmp / "m.npy"), "--out", str(tmp / "m.npy")], tmp / "m.npy"
    if name == "decode into its brick model folder":
        shutil.copytree(test_data / "reference_bricks", tmp / "bricks")
        return ["decode", str(tmp / "bricks"), "--out", str(tmp / "bricks" / "decoded.npy")], tmp / "bricks"
    if name == "info --plot onto its model":
        return ["info", str(m), "--plot", str(m)], m
    if name == "render onto its model":
        shutil.copy(m, tmp / "pic.png")
        return ["render", str(tmp / "pic.png"), "--out", str(tmp / "pic.png"), "--width", "8", "--height", "8"], \
            tmp / "pic.png"
    if name == "render --error-out onto the compared volume":
        return ["render", str(m), "--compare", str(v), "--out", str(tmp / "r.png"), "--error-out", str(v)], v
    if name == "render --save-tf onto its preset":
        shutil.copy(test_data / "render_reference_preset.json", tmp / "preset.json")
        return ["render", str(m), "--colormap", str(tmp / "preset.json"), "--save-tf", str(tmp / "preset.json"),
                "--out", str(tmp / "r.png")], tmp / "preset.json"
    if name == "grids whose picture is its model":
        shutil.copy(m, tmp / "g.png")
        return ["grids", str(tmp / "g.png"), str(v), "--out", str(tmp / "g")], tmp / "g.png"
    if name == "bench results folder onto its volume":
        return ["bench", "quality", str(v), "--out", str(v), "--iterations", "2"], v
    if name == "bench series results folder onto a step":
        for step in (0, 1):
            shutil.copy(v, tmp / f"s_{step}.npy")
        return ["bench", "series", str(tmp / "s_*.npy"), "--out", str(tmp / "s_1.npy"), "--iterations", "2"], \
            tmp / "s_1.npy"
    raise AssertionError(name)


@pytest.mark.parametrize("name", [
    "train onto its volume", "train through a .. path", "train onto a symbolic link to its volume",
    "train onto a hard link to its volume", "train whose checkpoint is its volume", "train bricks onto its volume",
    "decode onto its model", "decode into its brick model folder", "info --plot onto its model",
    "render onto its model", "render --error-out onto the compared volume", "render --save-tf onto its preset",
    "grids whose picture is its model", "bench results folder onto its volume",
    "bench series results folder onto a step",
])
def test_an_output_that_is_an_input_is_refused_and_the_input_kept(name, work, tmp_path, test_data, capsys):
    argv, source = _probe_case(name, work, tmp_path, test_data)
    before = digest(source)
    assert main(argv) == 2
    one_line_error(capsys, "would destroy the input", "choose another --")
    assert digest(source) == before


@pytest.mark.parametrize("command", ["decode", "info --plot", "render"])
def test_an_image_or_volume_never_replaces_a_model(command, work, tmp_path, capsys):
    other = tmp_path / ("other.npy" if command == "decode" else "other.png")
    shutil.copy(work / "m.apmgsrn", other)  # another model, named like the output
    argv = {"decode": ["decode", str(work / "m.apmgsrn"), "--out", str(other)],
            "info --plot": ["info", str(work / "m.apmgsrn"), "--plot", str(other)],
            "render": ["render", str(work / "m.apmgsrn"), "--out", str(other), "--width", "8", "--height", "8"]}
    assert main(argv[command]) == 2
    one_line_error(capsys, str(other), "is an apmgsrn model")
    assert other.read_bytes() == (work / "m.apmgsrn").read_bytes()


def test_a_model_replaces_an_older_model_but_no_other_file(work, tmp_path, capsys):
    out = tmp_path / "model.apmgsrn"
    assert main(["train", str(work / "v.npy"), "--out", str(out), *FAST]) == 0
    first = out.read_bytes()
    assert main(["train", str(work / "v.npy"), "--out", str(out), *FAST, "--seed", "1"]) == 0
    assert out.read_bytes() != first and apmgsrn.load(out).description.training["config"]["seed"] == 1
    notes = tmp_path / "notes.txt"
    notes.write_text("a week of measurements\n")
    capsys.readouterr()
    assert main(["train", str(work / "v.npy"), "--out", str(notes), *FAST]) == 2
    one_line_error(capsys, str(notes), "not an apmgsrn model", "--out")
    assert notes.read_text() == "a week of measurements\n"
    assert sorted(p.name for p in tmp_path.iterdir()) == ["model.apmgsrn", "notes.txt"]


def test_a_python_caller_cannot_save_a_model_over_a_volume_either(work, tmp_path):
    volume = tmp_path / "v.npy"
    shutil.copy(work / "v.npy", volume)
    with pytest.raises(ApmgsrnError, match="out=") as caught:
        save_field(volume, apmgsrn.load(work / "m.apmgsrn").field, SourceInfo(), {})
    assert "--" not in str(caught.value)
    assert volume.read_bytes() == (work / "v.npy").read_bytes()


def test_two_outputs_of_one_command_may_not_be_the_same_file(work, tmp_path, capsys):
    out = tmp_path / "r.png"
    assert main(["render", str(work / "m.apmgsrn"), "--compare", str(work / "v.npy"), "--out", str(out),
                 "--error-out", str(out)]) == 2
    one_line_error(capsys, "--out and --error-out")
    assert not out.exists()


# ------------------------------------------------------------------------------------------ item 4
TRAIN_PROBES = [
    (["--iterations", "0"], "--iterations"), (["--iterations", "-3"], "--iterations"),
    (["--batch-size", "0"], "--batch-size"), (["--batch-size", "10000000000"], "--batch-size"),
    (["--checkpoint-every", "0"], "--checkpoint-every"), (["--lr", "nan"], "--lr"), (["--lr", "-1"], "--lr"),
    (["--lr", "inf"], "--lr"), (["--placement-lr", "-0.1"], "--placement-lr"),
    (["--freeze-fraction", "nan"], "--freeze-fraction"), (["--freeze-fraction", "2"], "--freeze-fraction"),
    (["--density-start", "-1"], "--density-start"), (["--seed", "-1"], "--seed"),
    (["--backend", "tcnn"], "--backend"), (["--log-offset", "nan"], "--log-offset"),
    (["--fill-nonfinite", "inf"], "--fill-nonfinite"), (["--model", "apmgsrn", "--grids", "0"], None),
    (["--resolution", "0"], "--resolution"),
    (["--hidden-layers", "0"], None), (["--width", "100000"], None), (["--model", "ngp", "--levels", "2"], "--grids"),
    (["--model", "fvsrn", "--frequencies", "100000000"], "--grids"), (["--bricks", "0"], "--bricks"),
    (["--bricks", "2", "--ghost-cells", "-1"], "--ghost-cells"), (["--bricks", "2", "--workers", "0"], "--workers"),
    (["--bricks", "2", "--retries", "-1"], "--retries"),
    (["--bricks", "2", "--workers", "2", "--scheduler", "tcp://127.0.0.1:1"], "--scheduler"),
    (["--bricks", "64,1,1"], "--bricks"),
]


@pytest.mark.parametrize("probe, flag", TRAIN_PROBES, ids=[" ".join(p) for p, _ in TRAIN_PROBES])
def test_train_refuses_every_number_out_of_range(probe, flag, work, tmp_path, capsys):
    out = tmp_path / "m.apmgsrn"
    assert main(["train", str(work / "v.npy"), "--out", str(out), *FAST, *probe]) == 2
    one_line_error(capsys, *([flag] if flag else []))
    assert list(tmp_path.iterdir()) == []  # refused before anything was written


@pytest.mark.parametrize("probe", [["--model", "ngp", "--levels", "100000"], ["--model", "ngp", "--features", "0"],
                                   ["--model", "fvsrn", "--frequencies", "100000000"]], ids=" ".join)
def test_baseline_sizes_out_of_range_are_refused(probe, work, tmp_path, capsys):
    assert main(["train", str(work / "v.npy"), "--out", str(tmp_path / "m.apmgsrn"), "--iterations", "2", *probe]) == 2
    one_line_error(capsys, "invalid model or training options")
    assert list(tmp_path.iterdir()) == []


OTHER_PROBES = [
    (["decode", "{m}", "--out", "{tmp}/d.npy", "--batch-size", "-5"], "--batch-size"),
    (["decode", "{m}", "--out", "{tmp}/d.npy", "--batch-size", "0"], "--batch-size"),
    (["eval", "{m}", "{v}", "--batch-size", "-1"], "--batch-size"),
    (["eval", "{m}", "{v}", "--batch-size", "0"], "--batch-size"),
    (["render", "{m}", "--out", "{tmp}/r.png", "--width", "100000", "--height", "100000"], "--width"),
    (["render", "{m}", "--out", "{tmp}/r.png", "--height", "0"], "--height"),
    (["render", "{m}", "--out", "{tmp}/r.png", "--spp", "0"], "--spp"),
    (["render", "{m}", "--out", "{tmp}/r.png", "--reference-samples", "0"], "--reference-samples"),
    (["render", "{m}", "--out", "{tmp}/r.png", "--batch-size", "8"], "--batch-size"),
    (["render", "{m}", "--out", "{tmp}/r.png", "--early-termination", "1"], "--early-termination"),
    (["render", "{m}", "--out", "{tmp}/r.png", "--macro-cells", "0"], "--macro-cells"),
    (["render", "{m}", "--out", "{tmp}/r.png", "--fov", "180"], "--fov"),
    (["render", "{m}", "--out", "{tmp}/r.png", "--distance", "-1"], "--distance"),
    (["render", "{m}", "--out", "{tmp}/r.png", "--azimuth", "nan"], "--azimuth"),
    (["render", "{m}", "--out", "{tmp}/r.png", "--elevation", "inf"], "--elevation"),
    (["render", "{m}", "--out", "{tmp}/r.png", "--seed", "-1"], "--seed"),
    (["render", "{m}", "--out", "{tmp}/r.gif", "--frames", "0"], "--frames"),
    (["render", "{m}", "--out", "{tmp}/r.gif", "--frames", "2", "--fps", "0", "--width", "8", "--height", "8"],
     "--fps"),
    (["grids", "{m}", "{v}", "--out", "{tmp}/g", "--animate", "--every", "0"], "--every"),
    (["grids", "{m}", "{v}", "--out", "{tmp}/g", "--animate", "--iterations", "0"], "--iterations"),
    (["bench", "quality", "{v}", "--out", "{tmp}/b", "--seeds", "0"], "--seeds"),
    (["bench", "quality", "{v}", "--out", "{tmp}/b", "--iterations", "0"], "--iterations"),
    (["bench", "quality", "{v}", "--out", "{tmp}/b", "--batch-size", "0"], "--batch-size"),
    (["bench", "compress", "{v}", "--out", "{tmp}/b", "--bounds", "2"], "--bounds"),
    (["bench", "compress", "{v}", "--out", "{tmp}/b", "--query-points", "0"], "--query-points"),
    (["bench", "series", "{v}", "--out", "{tmp}/b", "--iterations", "0"], "--iterations"),
    (["bench", "series", "{v}", "--out", "{tmp}/b", "--batch-size", "0"], "--batch-size"),
    (["bench", "series", "{v}", "--out", "{tmp}/b", "--seeds", "0"], "--seeds"),
]


@pytest.mark.parametrize("probe, flag", OTHER_PROBES, ids=[" ".join(p[:1] + p[-2:]) for p, _ in OTHER_PROBES])
def test_every_other_command_refuses_numbers_out_of_range(probe, flag, work, tmp_path, capsys):
    argv = [a.format(m=work / "m.apmgsrn", v=work / "v.npy", tmp=tmp_path) for a in probe]
    assert main(argv) == 2
    one_line_error(capsys, flag)
    assert list(tmp_path.iterdir()) == []


@pytest.mark.parametrize("argv", [
    [], ["nosuch"], ["train"], ["train", "v.npy", "--out", "m", "--bogus"],
    ["train", "v.npy", "--out", "m", "--iterations", "abc"], ["train", "v.npy", "--out", "m", "--batch-size", "1e10"],
    ["train", "v.npy", "--out", "m", "--backend", "evil"], ["render", "m", "--out", "r.png", "--preset-units", "x"],
    ["bench"], ["bench", "quality"],
], ids=repr)
def test_argument_errors_are_one_line_too(argv, capsys):
    assert main(argv) == 2
    one_line_error(capsys, "--help")


# The library refuses the same values itself, naming its own arguments; the CLI only translates.
LIBRARY_PROBES = [
    ("lr", lambda: TrainConfig(lr=float("nan"))),
    ("batch_size", lambda: TrainConfig(batch_size=0)),
    ("iterations", lambda: TrainConfig(iterations=0)),
    ("checkpoint_every", lambda: TrainConfig(checkpoint_every=0)),
    ("freeze_fraction", lambda: TrainConfig(freeze_fraction=float("nan"))),
    ("lr_schedule", lambda: TrainConfig(lr_schedule="evil")),
    ("backend", lambda: preset_config("apmgsrn", "small", backend="evil")),
    ("batch_size", lambda: RendererConfig(batch_size=0)),
    ("samples_per_ray", lambda: RendererConfig(samples_per_ray=0)),
    ("width", lambda: Camera.orbit(width=100000)),
    ("fov", lambda: Camera.orbit(fov=float("nan"))),
    ("batch_size", lambda: query(torch.nn.Linear(3, 1), torch.zeros(4, 3), batch_size=-5)),
    ("bricks", lambda: DecompositionConfig((0, 1, 1))),
    ("ghost_cells", lambda: DecompositionConfig((2, 1, 1), ghost_cells=-1)),
    ("workers", lambda: ExecutorConfig(workers=0)),
    ("seeds", lambda: QualityPlan(datasets=(), seeds=0)),
    ("bounds", lambda: CompressPlan(DataSpec(Path("v.npy")), bounds=(2.0,))),
    ("log_offset", lambda: fit_value_transform("none", [], 0.0, offset=float("nan"))),
]


@pytest.mark.parametrize("name, make", LIBRARY_PROBES, ids=[name for name, _ in LIBRARY_PROBES])
def test_library_configs_refuse_bad_values_in_their_own_words(name, make):
    with pytest.raises(InvalidArgument) as caught:
        make()
    assert isinstance(caught.value, ValueError) and isinstance(caught.value, ApmgsrnError)
    message = str(caught.value)
    assert message.startswith(f"{name}=") and "--" not in message, message
    assert caught.value.arguments == (name,)


# ------------------------------------------------------------------------------------------ items 8 and 9
RESUMABLE = ["--grids", "2", "--resolution", "4", "--iterations", "40", "--batch-size", "512",
             "--checkpoint-every", "5", "--device", "cpu"]


class _CtrlCAt(TrainingCallback):
    """Presses Ctrl-C after a few iterations (the trainer then saves a checkpoint and stops)."""

    def __init__(self, *args, **kwargs):
        pass

    def after_step(self, trainer, iteration, losses) -> None:
        if iteration == 7:
            os.kill(os.getpid(), signal.SIGINT)


@pytest.fixture(scope="module")
def interrupted(work, tmp_path_factory) -> tuple[Path, Path]:
    """(volume, checkpoint) of a real run stopped by Ctrl-C at iteration 7, after the grids started moving."""
    folder = tmp_path_factory.mktemp("interrupted")
    with pytest.MonkeyPatch.context() as patch:
        patch.setattr(fit_module, "TrainingProgress", _CtrlCAt)
        # The paper's model, as before the default changed: the resumes below name no model and must find it.
        assert main(["train", str(work / "v.npy"), "--out", str(folder / "m.apmgsrn"), *RESUMABLE,
                     "--model", "apmgsrn"]) == 130
    checkpoint = folder / "m.apmgsrn.ckpt"
    with safe_open(str(checkpoint), "pt") as f:
        state = json.loads(f.metadata()["description"])["state"]
        assert state["iteration"] == 7 and state["density_steps"] > 0  # both optimisers have moments
    return work / "v.npy", checkpoint


def _tampered(checkpoint: Path, tmp_path: Path, change) -> Path:
    """A copy of the checkpoint as ``tmp_path/m.apmgsrn.ckpt``, passed through ``change(tensors, description)``."""
    with safe_open(str(checkpoint), "pt") as f:
        metadata = f.metadata()
        tensors = {name: f.get_tensor(name) for name in f.keys()}
    description = json.loads(metadata["description"])
    change(tensors, description)
    metadata["description"] = json.dumps(description)
    copy = tmp_path / "m.apmgsrn.ckpt"
    copy.write_bytes(sealed_file_bytes(tensors, metadata))  # checksums made anew
    return copy


def _set_state(field, value):
    return lambda tensors, description: description["state"].__setitem__(field, value)


TAMPERING = {
    "missing optimiser moment": lambda t, d: t.pop("optim.network.0.exp_avg"),
    "missing optimiser state": lambda t, d: [t.pop(k) for k in [k for k in t if k.startswith("optim.placement.")]],
    "extra optimiser state": lambda t, d: t.__setitem__("optim.network.99.exp_avg", torch.zeros(3)),
    "moment of the wrong shape": lambda t, d: t.__setitem__("optim.network.0.exp_avg_sq",
                                                            torch.zeros(*t["optim.network.0.exp_avg_sq"].shape, 2)),
    "weights of the wrong shape": lambda t, d: t.__setitem__("model.decoder.0.weight", torch.zeros(64, 3)),
    "weights of the wrong dtype": lambda t, d: t.__setitem__("model.decoder.0.weight",
                                                             t["model.decoder.0.weight"].double()),
    "generator state cut short": lambda t, d: t.__setitem__("generator", t["generator"][:100].clone()),
    "iteration 'abc'": _set_state("iteration", "abc"),
    "iteration beyond the budget": _set_state("iteration", 10**9),
    "frozen_at a string": _set_state("frozen_at", "abc"),
    "lr_scale a list": _set_state("lr_scale", [1.0]),
    "history a string": _set_state("history", "abc"),
    "history series of unequal length": lambda t, d: d["state"]["history"]["lr"].append(0.1),
    "state an integer": lambda t, d: d.__setitem__("state", 7),
    "state with an extra field": _set_state("surprise", 1),
}


@pytest.mark.parametrize("case", TAMPERING)
def test_a_tampered_checkpoint_is_refused_in_one_line_naming_it(case, interrupted, tmp_path, capsys):
    volume, checkpoint = interrupted
    copy = _tampered(checkpoint, tmp_path, TAMPERING[case])
    before = digest(copy)
    assert main(["train", str(volume), "--out", str(tmp_path / "m.apmgsrn"), *RESUMABLE, "--resume"]) == 2
    one_line_error(capsys, str(copy), "delete it to start over")
    assert digest(copy) == before and not (tmp_path / "m.apmgsrn").exists()


def test_the_untampered_checkpoint_resumes(interrupted, tmp_path):
    volume, checkpoint = interrupted
    copy = _tampered(checkpoint, tmp_path, lambda tensors, description: None)
    assert main(["train", str(volume), "--out", str(tmp_path / "m.apmgsrn"), *RESUMABLE, "--resume"]) == 0
    assert apmgsrn.load(tmp_path / "m.apmgsrn").description.training["iterations"] == 40
    assert not copy.exists()


def _older_names(tensors: dict, description: dict) -> None:
    """A checkpoint as versions before the grid-placement rename (and before voxel points) wrote it."""
    for name in [k for k in tensors if k.startswith("optim.placement.")]:
        tensors["optim.transform." + name[len("optim.placement."):]] = tensors.pop(name)
    config = description["config"]
    config["transform_lr"] = config.pop("placement_lr")
    del config["voxel_fraction"]


def test_a_checkpoint_with_the_older_names_resumes_to_the_same_model(interrupted, tmp_path):
    volume, checkpoint = interrupted
    _tampered(checkpoint, tmp_path, lambda tensors, description: None)
    assert main(["train", str(volume), "--out", str(tmp_path / "m.apmgsrn"), *RESUMABLE, "--resume"]) == 0
    older = tmp_path / "older"
    older.mkdir()
    _tampered(checkpoint, older, _older_names)
    assert main(["train", str(volume), "--out", str(older / "m.apmgsrn"), *RESUMABLE, "--resume"]) == 0
    assert apmgsrn.load(tmp_path / "m.apmgsrn").description.config.model == "apmgsrn"  # as the run began
    resumed, reference = load_file(str(older / "m.apmgsrn")), load_file(str(tmp_path / "m.apmgsrn"))
    assert resumed.keys() == reference.keys()
    assert all(torch.equal(resumed[name], reference[name]) for name in reference)


def test_resume_on_another_file_of_the_same_name_shape_and_dtype_is_refused(interrupted, tmp_path, capsys):
    volume, checkpoint = interrupted
    shutil.copy(checkpoint, tmp_path / "m.apmgsrn.ckpt")
    other = tmp_path / "run2" / volume.name
    other.parent.mkdir()
    shutil.copy(volume, other)  # the same bytes, even: another file
    assert main(["train", str(other), "--out", str(tmp_path / "m.apmgsrn"), *RESUMABLE, "--resume"]) == 2
    one_line_error(capsys, "other data or settings")
    # Through a symbolic link the same file resumes.
    (tmp_path / "link.npy").symlink_to(volume)
    assert main(["train", str(tmp_path / "link.npy"), "--out", str(tmp_path / "m.apmgsrn"), *RESUMABLE,
                 "--resume"]) == 0


def test_the_fingerprint_tells_files_apart_by_content_and_real_path(work, tmp_path):
    original = np.load(work / "v.npy")
    changed = original.copy()
    changed[16, 16, 16] ^= 1  # one voxel, one bit, in the centre block of the sample
    np.save(tmp_path / "a.npy", original)
    np.save(tmp_path / "b.npy", changed)
    (tmp_path / "c.npy").symlink_to(tmp_path / "a.npy")
    a, b, c = (volume_fingerprint(open_volume(tmp_path / name)) for name in ("a.npy", "b.npy", "c.npy"))
    assert a["sample_sha256"] != b["sample_sha256"] and a["shape"] == b["shape"] and a["dtype"] == b["dtype"]
    assert c == a and a["path"] == str((tmp_path / "a.npy").resolve())
    assert volume_fingerprint(open_volume(work / "v.npy"))["sample_sha256"] == a["sample_sha256"]


def test_a_brick_folder_is_not_finished_on_other_data(work, tmp_path):
    first, second = tmp_path / "run1" / "v.npy", tmp_path / "run2" / "v.npy"
    for path in (first, second):
        path.parent.mkdir()
    shutil.copy(work / "v.npy", first)
    np.save(second, np.load(first)[::-1].copy())  # same name, shape and dtype; other values
    field = preset_config("apmgsrn", "small", grids=2, resolution=(4, 4, 4), width=8)
    config = TrainConfig(iterations=4, batch_size=512)
    out = tmp_path / "bricks"

    def run(path):
        with open_job_queue(ExecutorConfig(use_dask=False, workers=1)) as queue:
            return train_bricks(open_volume(path), DecompositionConfig((2, 1, 1)), field, config, out, queue)

    assert run(first).complete
    before = digest(out)
    with pytest.raises(ApmgsrnError, match="other data .*sample_sha256.*same data file"):
        run(second)
    assert digest(out) == before
    assert run(first).complete  # the same data: nothing left to do, nothing refused


# ------------------------------------------------------------------------------------------ issue 12 item 6
def test_advice_names_the_library_argument_in_python_and_the_option_on_the_command_line(work, tmp_path, capsys):
    holes = np.load(work / "v.npy").astype(np.float32)
    holes[3, 4, 5] = np.nan
    np.save(tmp_path / "holes.npy", holes)
    with pytest.raises(ApmgsrnError) as caught:
        check_finite(open_volume(tmp_path / "holes.npy"))
    assert "pass fill_nonfinite=VALUE" in str(caught.value) and "--fill-nonfinite" not in str(caught.value)
    assert main(["train", str(tmp_path / "holes.npy"), "--out", str(tmp_path / "m.apmgsrn"), *FAST]) == 2
    line = one_line_error(capsys, "pass --fill-nonfinite VALUE", "(e.g. --fill-nonfinite 0)")
    assert "fill_nonfinite" not in line
    assert main(["train", str(work / "v.npy"), "--out", str(tmp_path / "m.apmgsrn"), *FAST, "--transform", "log10"]) == 2
    line = one_line_error(capsys, "--transform log10 needs values > 0", "pass --log-offset VALUE")
    assert "log_offset" not in line


def test_compression_is_reported_against_the_stored_dtype_and_float32(work, tmp_path, capsys):
    """A uint8 volume is 1 byte a voxel (SPEC section 8): the float32 figure alone overstated it 4x."""
    model_bytes = (work / "m.apmgsrn").stat().st_size
    voxels = 32**3
    assert main(["eval", str(work / "m.apmgsrn"), str(work / "v.npy"), "--json"]) == 0
    figures = json.loads(capsys.readouterr().out)
    assert figures["data_dtype"] == "uint8" and figures["data_bytes"] == voxels
    assert figures["compression_ratio"] == pytest.approx(voxels / model_bytes)
    assert figures["compression_ratio_float32"] == pytest.approx(4 * voxels / model_bytes)
    assert main(["eval", str(work / "m.apmgsrn"), str(work / "v.npy")]) == 0
    text = capsys.readouterr().out
    assert f"{voxels / model_bytes:.1f}x against the stored uint8 data, {4 * voxels / model_bytes:.1f}x against float32" \
        in text
    # info reads the stored dtype from the model file itself.
    assert main(["info", str(work / "m.apmgsrn"), "--json"]) == 0
    info = json.loads(capsys.readouterr().out)
    assert info["source"]["dtype"] == "uint8" and info["compression_ratio"] == pytest.approx(voxels / model_bytes)
    # A float32 volume has one figure.
    np.save(tmp_path / "f.npy", np.load(work / "v.npy").astype(np.float32))
    assert main(["train", str(tmp_path / "f.npy"), "--out", str(tmp_path / "f.apmgsrn"), *FAST]) == 0
    line = next(l for l in capsys.readouterr().out.splitlines() if l.startswith("compression"))
    ratio = 4 * voxels / (tmp_path / "f.apmgsrn").stat().st_size
    assert line == f"compression {ratio:.1f}x against the stored float32 data" and math.isfinite(ratio)


def test_an_npy_of_python_objects_is_refused_without_unpickling(work, tmp_path, capsys):
    marker = tmp_path / "ran"
    payload = np.empty((2, 2, 2), dtype=object)
    payload[0, 0, 0] = _Exploit(str(marker))
    np.save(tmp_path / "objects.npy", payload, allow_pickle=True)
    assert main(["train", str(tmp_path / "objects.npy"), "--out", str(tmp_path / "m.apmgsrn"), *FAST]) == 2
    one_line_error(capsys, "objects.npy")
    assert not marker.exists()


class _Exploit:
    """Unpickling this touches a marker file: what a crafted payload could do instead."""

    def __init__(self, marker: str):
        self.marker = marker

    def __reduce__(self):
        return (Path.touch, (Path(self.marker),))
