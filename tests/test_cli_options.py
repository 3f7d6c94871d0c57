"""The command line's options: ``--help`` without the library behind it, choice lists that are the library's
own, and errors that the library words for Python callers and the command line translates into options."""

from __future__ import annotations

import argparse
import ast
import json
import re
import subprocess
import sys
from pathlib import Path

import pytest

from apmgsrn import choices
from apmgsrn.cli.flags import FLAGS, cli_message
from apmgsrn.cli.main import build_parser
from apmgsrn.errors import ApmgsrnError

SRC = Path(__file__).resolve().parents[1] / "src" / "apmgsrn"


def subcommand_parsers() -> dict[str, argparse.ArgumentParser]:
    """``{"": top parser, "train": ..., "bench quality": ...}``: every parser of the command line."""
    found = {}

    def walk(name: str, parser: argparse.ArgumentParser) -> None:
        found[name] = parser
        for action in parser._actions:
            if isinstance(action, argparse._SubParsersAction):
                for child, sub in action.choices.items():
                    walk(f"{name} {child}".strip(), sub)

    walk("", build_parser())
    return found


def test_every_help_answers_without_importing_torch_or_numpy():
    """``--help`` of every (sub)command in one fresh interpreter: torch and numpy stay unloaded."""
    commands = [name.split() for name in subcommand_parsers()]
    script = (
        "import contextlib, io, json, sys\n"
        "from apmgsrn.cli.main import main\n"
        "codes = []\n"
        f"for command in {commands!r}:\n"
        "    with contextlib.redirect_stdout(io.StringIO()) as shown:\n"
        "        codes.append((command, main([*command, '--help']), len(shown.getvalue())))\n"
        "print(json.dumps({'codes': codes, 'torch': 'torch' in sys.modules, 'numpy': 'numpy' in sys.modules}))\n"
    )
    result = subprocess.run([sys.executable, "-c", script], capture_output=True, text=True, check=True,
                            env={"PYTHONPATH": str(SRC.parent), "PATH": "/usr/bin:/bin"})
    report = json.loads(result.stdout)
    assert len(report["codes"]) == len(commands) >= 11
    for command, code, length in report["codes"]:
        assert code == 0 and length > 200, command
    assert not report["torch"] and not report["numpy"]


def test_choice_lists_are_the_librarys():
    from apmgsrn.bench.compressors import COMPRESSORS
    from apmgsrn.models.encoders.adaptive_multigrid import GRID_INITS
    from apmgsrn.models.encoders.hash_grid import HASH_BACKENDS
    from apmgsrn.models.encoders.hybrid_grid import GRID_INITS as HYBRID_GRID_INITS
    from apmgsrn.models.registry import ENCODERS
    from apmgsrn.recipes import MODELS
    from apmgsrn.models.value_transform import TRANSFORMS
    from apmgsrn.ops.multigrid import BACKENDS
    from apmgsrn.rendering.paraview import PRESET_UNITS
    from apmgsrn.training.trainer import DECODER_PRECISIONS, DENSITY_NORMALIZATIONS, LR_SCHEDULES

    # The torch-free lists are what the library validates against (the encoders keep two copies: equal).
    assert tuple(ENCODERS) == choices.MODEL_KINDS
    assert tuple(MODELS) == choices.MODEL_KINDS
    assert all(tuple(MODELS[kind].presets) == choices.SIZE_PRESETS for kind in choices.MODEL_KINDS)
    assert GRID_INITS == choices.GRID_INITS and BACKENDS == choices.MULTIGRID_BACKENDS
    assert HYBRID_GRID_INITS == choices.HYBRID_GRID_INITS
    assert choices.BACKENDS["ngp"] == HASH_BACKENDS
    for kind, (config_class, _) in ENCODERS.items():
        assert config_class().backend == choices.BACKENDS[kind][0]  # the help says "default: the first"
    assert TRANSFORMS == choices.VALUE_TRANSFORMS and PRESET_UNITS == choices.PRESET_UNITS
    assert (LR_SCHEDULES, DENSITY_NORMALIZATIONS, DECODER_PRECISIONS) == (
        choices.LR_SCHEDULES, choices.DENSITY_NORMALIZATIONS, choices.DECODER_PRECISIONS)
    assert tuple(COMPRESSORS) == choices.COMPRESSORS

    # Every option with a choice list offers exactly one of those lists.
    expected = {
        "--model": choices.MODEL_KINDS, "--models": choices.MODEL_KINDS, "--preset": choices.SIZE_PRESETS,
        "--sizes": choices.SIZE_PRESETS,
        "--grid-init": tuple(dict.fromkeys(choices.GRID_INITS + choices.HYBRID_GRID_INITS)),
        "--backend": tuple(dict.fromkeys(b for names in choices.BACKENDS.values() for b in names)),
        "--transform": choices.VALUE_TRANSFORMS, "--lr-schedule": choices.LR_SCHEDULES,
        "--density-normalization": choices.DENSITY_NORMALIZATIONS,
        "--decoder-precision": choices.DECODER_PRECISIONS, "--precision": choices.DECODER_PRECISIONS,
        "--preset-units": choices.PRESET_UNITS,
        "--compressors": choices.COMPRESSORS, "--region-units": choices.REGION_UNITS,
        "--format": choices.EXPORT_FORMATS, "--coefficients": choices.SERIES_COEFFICIENTS,
        "--storage": choices.SERIES_STORAGE, "--series-training": choices.SERIES_TRAINING,
        "--vtk-coordinates": ("index", "normalized"),  # the grids command's own: no library list behind it
    }
    seen = set()
    for name, parser in subcommand_parsers().items():
        for action in parser._actions:
            if action.choices is None or isinstance(action, argparse._SubParsersAction):
                continue
            option = action.option_strings[-1]
            assert tuple(action.choices) == expected[option], (name, option)
            seen.add(option)
    assert seen == set(expected)


def test_every_flag_of_the_translation_table_exists():
    options = {o for parser in subcommand_parsers().values() for a in parser._actions for o in a.option_strings}
    assert set(FLAGS.values()) <= options, set(FLAGS.values()) - options


def test_translation_rewrites_only_the_arguments_an_error_names():
    error = ApmgsrnError("x.npy: pass resume=True or lr=0.1; keep out=; the file a lr=2.nc stays, "
                         "fill_nonfinite=VALUE (e.g. fill_nonfinite=0); my_lr=3", arguments=("resume", "lr", "out",
                                                                                                "fill_nonfinite"))
    assert cli_message(error) == ("x.npy: pass --resume or --lr 0.1; keep --out; the file a --lr 2.nc stays, "
                                  "--fill-nonfinite VALUE (e.g. --fill-nonfinite 0); my_lr=3")
    untouched = ApmgsrnError("m.apmgsrn: model file is inconsistent (DecoderConfig(hidden_layers=0, width=64))")
    assert cli_message(untouched) == str(untouched)


#: Arguments of library configs that no command-line option sets (their errors reach Python callers only).
LIBRARY_ONLY = {
    "betas", "density_window", "density_tolerance", "density_power", "final_lr_fraction", "history_every",
    "stop_after_lr_cuts", "samples_per_cell", "table_size", "points", "qat_lr", "sensitivity_points",
    "measure_voxels",
    "steps", "mixing",  # a series' step count comes from its data; weight lattices are a library option
    "min_bits",  # the smallest bit width a series' size target may lower to
    "finer",  # the fraction of a bit a series' size target refines its bit width by (the packer chooses it)
    "placement",  # a series' placement per step: what stepwise training fills, not a choice on the command line
    "placement_loss",  # the reconstruction error moves a drifting step's placement (stepwise training decides)
    "error_measurements", "error_parts",  # how often the error guide measures, and in how many parts (training
    # sets them per kind of run: one volume, a series' step, its quantisation-aware fine-tune)
}
CHECKS = {"check_int", "check_optional_int", "check_number", "check_choice"}


def _library_modules():
    for path in sorted(SRC.rglob("*.py")):
        if {"cli", "viewer"} & set(path.relative_to(SRC).parts):
            continue  # the command line itself, and the viewer (which speaks to its own users)
        yield path, ast.parse(path.read_text(), str(path))


def _strings(node) -> list[str]:
    return [n.value for n in ast.walk(node) if isinstance(n, ast.Constant) and isinstance(n.value, str)]


def test_library_errors_name_arguments_not_options():
    """No message the library raises names an apmgsrn option; every argument it names as ``name=`` that the
    command line sets has its option in the table."""
    options = {o for parser in subcommand_parsers().values() for a in parser._actions for o in a.option_strings
               if o.startswith("--") and o != "--help"}
    option_pattern = re.compile("|".join(rf"(?<![\w-]){re.escape(o)}(?![\w-])" for o in sorted(options)))
    offending, unmapped = [], set()
    for path, tree in _library_modules():
        for node in ast.walk(tree):
            if isinstance(node, ast.Raise):
                for text in _strings(node):
                    if option_pattern.search(text):
                        offending.append(f"{path.relative_to(SRC)}:{node.lineno}: {text!r}")
            if isinstance(node, ast.Call):
                name = getattr(node.func, "id", getattr(node.func, "attr", ""))
                named = []
                if name in CHECKS and node.args and isinstance(node.args[0], ast.Constant):
                    named.append(node.args[0].value)
                for keyword in node.keywords:
                    if keyword.arg == "arguments":
                        named += [s for s in _strings(keyword.value)]
                unmapped |= {n for n in named if n not in FLAGS and n not in LIBRARY_ONLY}
    assert offending == []
    assert unmapped == set()


@pytest.mark.parametrize("command", [["train"], ["decode"], ["export"], ["render"], ["info"], ["bench", "quality"]])
def test_help_says_what_an_output_may_replace(command, capsys):
    from apmgsrn.cli.main import main

    assert main([*command, "--help"]) == 0
    text = " ".join(capsys.readouterr().out.split())
    assert "replaced" in text or "rewritten" in text
