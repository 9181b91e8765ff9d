"""Figures sized for the screen: the page embeds each figure at most MAX_WIDTH pixels wide and about
EMBED_LIMIT bytes (renders as JPEG, plots as palette PNG, the animation with smaller frames), and a click opens
the full-size picture, a file beside the page: the render itself where it lies under OUT (data/renders/...),
else ``OUT/figures/<section>-<n>.<ext>`` written by :func:`place_images`.  A figure already small enough is
embedded as it is and opens full size in the page."""
from __future__ import annotations

import base64
import io
from pathlib import Path

from PIL import Image, ImageSequence

from cloudpbf_io.files import atomic_write_bytes

MAX_WIDTH = 1000        # px: the widest figure a section shows at 1366 px
EMBED_LIMIT = 120_000   # bytes: a larger figure is shrunk for the page
GIF_WIDTH = 480         # px: the embedded animation's frames
JPEG_QUALITY = 82
FIGURES = "figures"     # OUT/figures: full-size files of shrunk figures that are not already under OUT


def decode(uri: str) -> tuple[str, bytes]:
    """(mime type, bytes) of a base64 data URI."""
    head, data = uri.split(",", 1)
    return head[len("data:"):].split(";")[0], base64.b64decode(data)


def encode(mime: str, raw: bytes) -> str:
    return f"data:{mime};base64," + base64.b64encode(raw).decode("ascii")


def _resized(im: Image.Image, width: int) -> Image.Image:
    if im.width <= width:
        return im
    return im.resize((width, max(1, round(im.height * width / im.width))), Image.LANCZOS)


def _flat(im: Image.Image) -> Image.Image:
    """RGB on white (plots and renders with an alpha channel)."""
    if im.mode in ("RGBA", "LA", "P"):
        im = im.convert("RGBA")
        back = Image.new("RGB", im.size, (255, 255, 255))
        back.paste(im, mask=im.split()[-1])
        return back
    return im.convert("RGB")


def screen_version(raw: bytes, mime: str) -> str | None:
    """The figure as the page embeds it (a data URI), or None where `raw` is already small enough."""
    im = Image.open(io.BytesIO(raw))
    if len(raw) <= EMBED_LIMIT and im.width <= MAX_WIDTH:
        return None
    buf = io.BytesIO()
    if getattr(im, "is_animated", False):
        frames = [_resized(_flat(f), GIF_WIDTH).quantize(colors=128) for f in ImageSequence.Iterator(im)]
        frames[0].save(buf, format="GIF", save_all=True, append_images=frames[1:], loop=0,
                       duration=im.info.get("duration", 300), optimize=True)
        return encode("image/gif", buf.getvalue())
    flat = _resized(_flat(im), MAX_WIDTH)
    if flat.getcolors(maxcolors=2048) is None:          # a picture (a render): JPEG
        flat.save(buf, format="JPEG", quality=JPEG_QUALITY, optimize=True)
        return encode("image/jpeg", buf.getvalue())
    flat.quantize(colors=256).save(buf, format="PNG", optimize=True)     # a plot: few colours, sharp lines
    return encode("image/png", buf.getvalue())


def place_images(sections, out: Path) -> None:
    """Shrink every image block of `sections` that is too large for the page and set its ``full`` link: the
    file it came from when under `out`, else a file written to OUT/figures (whose stale files from earlier
    builds are removed)."""
    out = Path(out).resolve()
    folder = out / FIGURES
    written = set()
    for sec in sections:
        n = 0
        for block in sec.blocks:
            if block.kind != "image" or not isinstance(block.content, str):
                continue
            n += 1
            mime, raw = decode(block.content)
            shown = screen_version(raw, mime)
            if shown is None:
                continue
            block.content = shown
            source = Path(block.source).resolve() if block.source else None
            if source is not None and source.is_file() and out in source.parents:
                block.full = source.relative_to(out).as_posix()
                continue
            name = f"{sec.id}-{n}.{mime.split('/')[-1]}"
            folder.mkdir(exist_ok=True)
            atomic_write_bytes(folder / name, raw)
            written.add(name)
            block.full = f"{FIGURES}/{name}"
    if folder.is_dir():
        for old in folder.iterdir():
            if old.is_file() and old.name not in written:
                old.unlink()
