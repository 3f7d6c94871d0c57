"""glibc's allocator keeps freed memory for the next training step (apmgsrn.allocator)."""

import json
import os
import platform
import subprocess
import sys

import pytest

from apmgsrn.allocator import ALLOCATOR_VARIABLES

pytestmark = pytest.mark.skipif(platform.system() != "Linux" or platform.libc_ver()[0] != "glibc",
                                reason="glibc's mallopt only")

# Minor page faults of one pass of a hybrid model's encoder and decoder (PyTorch's matrix products, as a training
# step runs them) over every voxel of a 64^3 lattice in chunks of 8,192 points, after a first pass (the fewest of
# three); SETUP chooses the allocator.
FAULTS = """
SETUP
import json, resource, torch
from apmgsrn.models.field import NeuralField
from apmgsrn.models.registry import preset_config
from apmgsrn.ops.trilinear import voxel_coordinates
torch.set_num_threads(1)
field = NeuralField(preset_config("hybrid", "small"), fit_min=0, fit_max=1, volume_shape=(64, 64, 64),
                    generator=torch.Generator().manual_seed(0))
points = voxel_coordinates((64, 64, 64))
def one_pass():
    with torch.no_grad():
        return [field.decoder(field.encoder(part)) for part in points.split(8192)]
one_pass()
counts = []
for _ in range(3):  # the fewest of three passes: a one-off fault elsewhere in the process does not count
    before = resource.getrusage(resource.RUSAGE_SELF).ru_minflt
    one_pass()
    counts.append(resource.getrusage(resource.RUSAGE_SELF).ru_minflt - before)
print(json.dumps({"faults": min(counts)}))
"""


def _run(code: str, **env) -> str:
    clean = {k: v for k, v in os.environ.items() if k not in ALLOCATOR_VARIABLES}
    result = subprocess.run([sys.executable, "-c", code], env={**clean, **env}, capture_output=True, text=True,
                            check=True, timeout=120)
    return result.stdout.strip().splitlines()[-1]


def _faults(setup: str, **env) -> int:
    return json.loads(_run(FAULTS.replace("SETUP", setup), **env))["faults"]


def test_import_keeps_freed_blocks_mapped_where_glibc_maps_them_afresh():
    ours = _faults("import apmgsrn")
    defaults = _faults("", GLIBC_TUNABLES="")  # apmgsrn's import then leaves glibc's own settings
    hidden_layer_pages = 8192 * 64 * 4 // 4096  # one chunk's [8192, 64] float32 activations
    assert defaults > 4 * hidden_layer_pages  # blocks of a few MB faulted in again and again
    assert ours < defaults / 10


def test_the_user_settings_stand():
    show = "import apmgsrn.allocator as a; print(a.keep_freed_memory())"
    assert _run(show) == "True"
    for name, value in (("MALLOC_TRIM_THRESHOLD_", "131072"), ("MALLOC_MMAP_THRESHOLD_", "131072"),
                        ("GLIBC_TUNABLES", "glibc.malloc.trim_threshold=131072")):
        assert _run(show, **{name: value}) == "False"
