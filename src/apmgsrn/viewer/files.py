"""What the viewer writes on the server (saved frames and transfer functions) and reads from the page
(uploaded presets, parsed in memory: an upload never reaches the disk)."""

from __future__ import annotations

import base64
import io
import re
import time
from pathlib import Path

import numpy as np
from PIL import Image

from apmgsrn.errors import ApmgsrnError
from apmgsrn.rendering import TransferFunction, save_transfer_function
from apmgsrn.rendering.paraview import PRESET_SUFFIXES, ParaViewPreset, parse_presets
from apmgsrn.sources import RenderSource
from apmgsrn.viewer.worker import Frame


def encode_image(image: np.ndarray, lossless: bool) -> bytes:
    """PNG (lossless) or JPEG bytes of an ``[H, W, 3]`` uint8 image.

    Args:
        image: the frame.
        lossless: PNG when True, else JPEG at quality 85.

    Returns:
        The encoded file's bytes.
    """
    buffer = io.BytesIO()
    picture = Image.fromarray(np.ascontiguousarray(image))
    if lossless:
        picture.save(buffer, format="PNG", compress_level=3)
    else:
        picture.save(buffer, format="JPEG", quality=85)
    return buffer.getvalue()


def safe_stem(text: str) -> str:
    """A file-name stem from any text: letters, digits, ``_.-`` only."""
    return re.sub(r"[^A-Za-z0-9_.-]+", "_", text).strip("._") or "view"


def uploaded_presets(name, text, max_bytes: int) -> list[ParaViewPreset]:
    """The colour-map presets of an uploaded ParaView file, parsed from its text (JSON or XML, never run).

    Args:
        name: the uploaded file's name (a label; its suffix picks the format).
        text: its content.
        max_bytes: larger uploads are refused.

    Returns:
        The continuous presets in the file.

    Raises:
        ApmgsrnError: not a name and text, too large, not ``.json``/``.xml``, or not a preset file.
    """
    if not isinstance(name, str) or not isinstance(text, str):
        raise ApmgsrnError("upload refused: expected a file name and its text")
    label = name[:200]
    if len(text) > max_bytes or len(text.encode("utf-8", "surrogatepass")) > max_bytes:
        raise ApmgsrnError(f"{label}: larger than the upload limit of {max_bytes:,} bytes; not a preset")
    if not label.lower().endswith(PRESET_SUFFIXES):
        raise ApmgsrnError(f"{label}: upload a ParaView colour-map preset (.json or .xml)")
    return parse_presets(text, label)


class SaveFolder:
    """The server-side folder of saved frames and transfer functions."""

    def __init__(self, directory: Path) -> None:
        """Args:
        directory: where saves go (created on the first save).
        """
        self.directory = Path(directory)

    def save_frame(self, frame: Frame, source: RenderSource | None) -> dict:
        """Write a frame (overlay included) as PNG.

        Returns:
            ``{"name", "data" (base64 PNG), "path"}`` for the page's download.
        """
        stem = safe_stem(Path(source.name).stem if source else "view")
        name = f"{stem}_{time.strftime('%Y%m%d-%H%M%S')}_{frame.generation}.png"
        data = encode_image(frame.image, lossless=True)
        path = self._folder() / name
        temporary = path.with_name(f".{path.name}.tmp")
        temporary.write_bytes(data)
        temporary.replace(path)  # atomic: a reader never sees half a PNG
        return {"name": name, "data": base64.b64encode(data).decode("ascii"), "path": str(path)}

    def save_transfer_function(self, transfer_function: TransferFunction, source: RenderSource | None) -> dict:
        """Write a transfer function as a ParaView preset.

        Returns:
            ``{"name", "data" (base64 JSON), "path"}`` for the page's download.
        """
        stem = safe_stem(Path(source.name).stem if source else "view")
        name = f"{stem}_transfer_function_{time.strftime('%Y%m%d-%H%M%S')}.json"
        path = save_transfer_function(transfer_function, self._folder() / name, name=f"apmgsrn {stem}")
        return {"name": name, "data": base64.b64encode(path.read_bytes()).decode("ascii"), "path": str(path)}

    def _folder(self) -> Path:
        try:
            self.directory.mkdir(parents=True, exist_ok=True)
        except OSError as exc:
            raise ApmgsrnError(
                f"{self.directory}: cannot create the save folder ({exc.strerror}); pass another --save-dir"
            ) from None
        return self.directory
