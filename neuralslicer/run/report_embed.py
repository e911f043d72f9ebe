"""A report's figures embedded in its Markdown (a Prefect artifact: the UI cannot follow a relative link), with PIL
only: a cached rerun publishes its report without the plotting libraries."""
from __future__ import annotations

import base64
import io
import re
from pathlib import Path

#: a report's figures embedded in one Markdown text (a Prefect artifact): at most this wide, at most this many bytes
#: of base64 in all (the figures past it are named, not embedded)
EMBED_WIDTH_PX = 720
EMBED_BUDGET_BYTES = 1_500_000
_IMAGE_LINK = re.compile(r"!\[([^\]]*)\]\(([^)\s]+)\)")


def embedded_png(path: Path, max_width_px: int = EMBED_WIDTH_PX) -> bytes:
    """A PNG of the picture at ``path`` at most ``max_width_px`` wide, in a 256-colour palette (a figure's flat
    colours survive it), for embedding."""
    from PIL import Image

    with Image.open(path) as img:
        img = img.convert("RGB")
        if img.width > max_width_px:
            img = img.resize((max_width_px, max(1, round(img.height * max_width_px / img.width))),
                             Image.Resampling.LANCZOS)
        buf = io.BytesIO()
        img.quantize(colors=256).save(buf, format="PNG", optimize=True)
    return buf.getvalue()


def embed_figures(markdown: str, folder: Path, max_width_px: int = EMBED_WIDTH_PX,
                  budget_bytes: int = EMBED_BUDGET_BYTES) -> str:
    """The Markdown with every relative image link (``![caption](figures/x.png)``, relative to ``folder``) replaced by
    the picture itself, a ``data:image/png;base64`` URI of :func:`embedded_png`, in order while ``budget_bytes``
    last; a figure past the budget, or unreadable, becomes a line naming its file. Other links are left alone."""
    spent = 0

    def embed(match: re.Match[str]) -> str:
        """One image link, embedded or named."""
        nonlocal spent
        caption, target = match.group(1), match.group(2)
        if target.startswith("data:") or "://" in target:
            return match.group(0)
        path = Path(folder) / target
        try:
            uri = "data:image/png;base64," + base64.b64encode(embedded_png(path, max_width_px)).decode()
        except (OSError, ValueError):
            return f"*{caption}: `{path}` (not readable)*"
        if spent + len(uri) > budget_bytes:
            return f"*{caption}: `{path}` (not embedded: the report's figures are over {budget_bytes // 1000} kB)*"
        spent += len(uri)
        return f"![{caption}]({uri})"

    return _IMAGE_LINK.sub(embed, markdown)
