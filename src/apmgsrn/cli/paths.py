"""What each command reads and writes, and the one check that it never writes onto what it reads.

Every subcommand that writes declares its files (``paths(args) -> CommandPaths``, set as the parser's
``paths`` default); :func:`check_paths` runs on them before any work. An output is refused when it is an
input or lies inside an input folder (a Zarr store, a brick model) under any spelling: the same path, a
``..`` detour, a symbolic link or a hard link. Every output passes the library's output gate
(:func:`apmgsrn.atomic.check_output_target`): never a device, named pipe or socket, never inside a model folder
(a brick model's manifest or bricks); an output whose suffix names its format must carry one of its suffixes.
An output that is not a model is also refused where an apmgsrn model lies: an image, plot or decoded volume
never replaces hours of training. What a model output may replace (an older model of its kind, never another
file) the library decides when it writes.
"""

from __future__ import annotations

import os
from collections.abc import Sequence
from dataclasses import dataclass
from pathlib import Path

from apmgsrn.atomic import check_output_target, check_suffix
from apmgsrn.errors import ApmgsrnError


@dataclass(frozen=True)
class Output:
    """A file or folder a command writes.

    Attributes:
        path: where.
        option: the option that names it (``--out``), for messages.
        what: what it is (``"image"``, ``"plot"``), for messages.
        model: a model file or brick-model folder (replacing an older model is then the library's call).
        suffixes: the suffixes naming the formats it may be written in (empty: any name).
    """

    path: str | os.PathLike
    option: str
    what: str
    model: bool = False
    suffixes: tuple[str, ...] = ()


@dataclass(frozen=True)
class CommandPaths:
    """The inputs and outputs of one command line."""

    reads: Sequence[str | os.PathLike] = ()
    writes: Sequence[Output] = ()


def check_paths(paths: CommandPaths) -> None:
    """Refuse outputs that would overwrite an input, a model, a part of a model, a file that is not a regular
    file, or each other, and outputs without the suffix of their format.

    Raises:
        ApmgsrnError: one line naming the output, the input it would destroy and the option to change.
    """
    if not paths.writes:
        return
    import apmgsrn.series  # noqa: F401 - registers the time-series kinds, so model_kind knows them
    from apmgsrn.io import model_kind  # reads a header only; torch comes with it, so not at start-up

    reads = [Path(p) for p in paths.reads if p is not None]
    seen: dict[str, Output] = {}
    for output in paths.writes:
        target = Path(output.path)
        for source in reads:
            overlap = overlap_with(target, source)
            if overlap:
                raise ApmgsrnError(
                    f"{target}: {overlap} {source}; writing the {output.what} there would destroy the input: "
                    f"choose another {output.option}"
                )
        check_output_target(target, output.what, option=output.option)  # before model_kind opens the file
        if not output.model and target.exists() and model_kind(target) is not None:
            raise ApmgsrnError(
                f"{target}: is an apmgsrn model; the {output.what} would replace it: choose another {output.option}"
            )
        if output.suffixes:
            check_suffix(target, output.suffixes, output.what, output.option)
        key = os.path.realpath(target)
        if key in seen:
            raise ApmgsrnError(
                f"{target}: named by both {seen[key].option} and {output.option}; one would overwrite the other: "
                f"choose another {output.option}"
            )
        seen[key] = output


def overlap_with(output: Path, source: Path) -> str | None:
    """How writing ``output`` would change ``source``: ``"is the input"`` (the same file under any name:
    links, ``..``), ``"lies inside the input"`` (a path inside the folder ``source``), or None."""
    real_output, real_source = os.path.realpath(output), os.path.realpath(source)
    if real_output == real_source:
        return "is the input"
    try:
        if output.exists() and source.exists() and os.path.samefile(output, source):
            return "is the input"  # a hard link: two names, one file
    except OSError:
        pass
    if source.is_dir() and Path(real_output).is_relative_to(real_source):
        return "lies inside the input"
    return None
