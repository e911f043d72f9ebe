"""``preview.html``: a self-contained page that back-plots a machine program through the profile's forward
kinematics in the part frame (layer range, colour by layer / tool tilt / feed / bead width, travels, the head at a
chosen move, collisions), decimated for display (:mod:`.data`), drawn by the plotly package's plotly.js
(:mod:`.page`: ``write_preview``). This module holds only the defaults, so that the command line reads them cheaply.
"""
from __future__ import annotations

#: the file name of the page, beside print.gcode
PREVIEW_FILE = "preview.html"
#: at most this many moves kept in the page by default
DEFAULT_MAX_POINTS = 300_000
#: at most this many moves drawn at once by default: a wider layer range draws a coarser level
DEFAULT_DRAW_BUDGET = 40_000
