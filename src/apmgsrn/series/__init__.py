"""Time series: everything only a run of several steps on one grid needs, on top of the core layers.

The core (``ops``, ``data``, ``models``, ``io``, ``training``, ``inference``, ``render``, ``decomposition``) knows
no series (an import-linter contract checks it); this package builds on it through its extension points and
registers itself with them on import:

- :mod:`~apmgsrn.series.data`: series of volumes (several files, a time axis, a ``.pvd``), their fingerprint;
- :mod:`~apmgsrn.series.options`, :mod:`~apmgsrn.series.field`, :mod:`~apmgsrn.series.hybrid`: the series field
  and its options (its field class registered with :func:`apmgsrn.training.fit.register_field_class`);
- :mod:`~apmgsrn.series.steps`, :mod:`~apmgsrn.series.fit`: stepwise and joint training, the series' end of
  :func:`apmgsrn.training.fit.fit` (:class:`~apmgsrn.series.fit.SeriesOutput`);
- :mod:`~apmgsrn.series.packing`, :mod:`~apmgsrn.series.qat`, :mod:`~apmgsrn.series.decoder`: series packing and
  the fine-tunes towards it;
- :mod:`~apmgsrn.series.file`, :mod:`~apmgsrn.series.packed_file`, :mod:`~apmgsrn.series.folder`: the
  ``series`` and ``packed-series`` files and the ``series-bricks`` folder (loaders registered with
  :func:`apmgsrn.io.register_loader`, the folder with :func:`apmgsrn.io.register_folder_kind`, the brick files'
  kinds with :func:`apmgsrn.io.brick_folder.register_brick_file_kind`);
- :mod:`~apmgsrn.series.bricks`: series on bricks, (brick, group of steps) jobs of the brick job kind
  :class:`~apmgsrn.series.bricks.SeriesBricks`;
- :mod:`~apmgsrn.series.evaluate`, :mod:`~apmgsrn.series.decode`: evaluation per step and decoding with a time axis.

:mod:`apmgsrn.api` imports this package, so :func:`apmgsrn.load` (and every command) opens every series kind.
"""

from apmgsrn.io import register_folder_kind, register_loader
from apmgsrn.io.brick_folder import register_brick_file_kind
from apmgsrn.io.container import PACKED_SERIES_KIND, SERIES_KIND
from apmgsrn.series.bricks import load_series_bricks
from apmgsrn.series.field import SeriesField, SeriesFieldConfig
from apmgsrn.series.file import load_series
from apmgsrn.series.folder import SERIES_BRICKS_KIND, is_series_brick_folder, read_series_manifest
from apmgsrn.series.packed_file import load_packed_series
from apmgsrn.training.fit import register_field_class

register_loader(SERIES_KIND, lambda path, device: load_series(path, device))
register_loader(PACKED_SERIES_KIND, lambda path, device: load_packed_series(path, device))
register_loader(SERIES_BRICKS_KIND, load_series_bricks)
register_folder_kind(SERIES_BRICKS_KIND, is_series_brick_folder, read_series_manifest)
for _kind in (SERIES_KIND, PACKED_SERIES_KIND):
    register_brick_file_kind(_kind)
register_field_class(SeriesFieldConfig, SeriesField)
