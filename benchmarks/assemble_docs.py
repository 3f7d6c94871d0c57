"""Assemble docs/benchmarks.md and docs/results.md from the per-topic files the benchmark scripts write.

Each benchmark script writes its own file (``docs/benchmarks_<topic>.md``, ``docs/results_<topic>.md``), so
a run on one machine replaces only its own tables. This script joins them, headings moved one level down,
under a short preamble: run it after any benchmark.

    python benchmarks/assemble_docs.py
"""

from __future__ import annotations

import re
from pathlib import Path

DOCS = Path(__file__).resolve().parents[1] / "docs"

PARTS = {
    "benchmarks.md": (
        "# Benchmarks\n\nTimings, memory and throughput, each table with the machine it was measured on and the "
        "command that made it. Joined by `benchmarks/assemble_docs.py` from the files below (edit those, or "
        "rerun their scripts).\n",
        ["benchmarks_core.md", "benchmarks_decode.md", "benchmarks_allocator.md", "benchmarks_contention.md",
         "benchmarks_encoder.md", "benchmarks_render.md", "benchmarks_bricks.md", "benchmarks_step_updates.md",
         "benchmarks_train_step.md"],
    ),
    "results.md": (
        "# Results\n\nQuality figures: PSNR of every shared volume under the authors' CPU protocol, the "
        "comparison with other networks and compressors, renders, and bricks. Joined by "
        "`benchmarks/assemble_docs.py` from the files below (edit those, or rerun their scripts). These are "
        "the paper's APMGSRN and its baselines; the default model since 2026-11-24, the hybrid, is measured "
        "against them in [models.md](models.md).\n",
        ["results_core.md", "results_protocol_cpu.md", "results_baselines.md", "results_render.md",
         "results_bricks.md"],
    ),
}


def demote(text: str) -> str:
    """Move every Markdown heading one level down, so that each part becomes a section."""
    return re.sub(r"^(#{1,5}) ", r"#\1 ", text, flags=re.M)


def assemble(name: str) -> str:
    preamble, files = PARTS[name]
    sections = [preamble, "Parts: " + ", ".join(f"[{f}]({f})" for f in files) + ".\n"]
    for file in files:
        text = (DOCS / file).read_text().strip()
        if not text.startswith("#"):
            text = f"# {file}\n\n{text}"
        sections.append(demote(text) + "\n")
    return "\n".join(sections)


def main() -> None:
    for name in PARTS:
        (DOCS / name).write_text(assemble(name))
        print(f"wrote {DOCS / name}")


if __name__ == "__main__":
    main()
