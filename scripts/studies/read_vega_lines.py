"""Read the lines of a Vega line chart saved as SVG at given x values (how the README's published anchors at a
budget were read off a peer's figure).

    python scripts/studies/read_vega_lines.py fig3_mt10.svg --at 1.0

The axes are calibrated from their tick marks and labels (``1M``, ``2M``, ... on x, in millions; ``0.2``, ... on y);
each line is the on-curve points of its path (the end point of every segment), read by linear interpolation. A
line's legend value comes from its ``aria-label`` (``Width: 256``). Vega clips a line to the plot, so a value below
the y axis's lower end reads as that end.
"""

from __future__ import annotations

import argparse
import re
from pathlib import Path

import numpy as np

TICK = r'<line transform="translate\(([-\d.]+),([-\d.]+)\)"'


def axis_fits(svg: str) -> tuple[np.ndarray, np.ndarray]:
    """Linear maps pixel -> value for x and y, from each axis's tick marks paired with its labels in order (a tick
    without a label, such as an unlabelled 0, is dropped from the front)."""
    x_ticks = [float(x) for x, _ in re.findall(TICK + r' x2="0" y2="5"', svg)]
    y_ticks = [float(y) for _, y in re.findall(TICK + r' x2="-5"', svg)]
    labels = re.findall(r"<text[^>]*>([^<]+)</text>", svg)
    x_values = [float(t[:-1]) for t in labels if re.fullmatch(r"\d+(\.\d+)?M", t)]
    y_values = [float(t) for t in labels if re.fullmatch(r"[01]\.\d+", t)]
    x_ticks, y_ticks = x_ticks[len(x_ticks) - len(x_values) :], y_ticks[len(y_ticks) - len(y_values) :]
    return np.polyfit(x_ticks, x_values, 1), np.polyfit(y_ticks, y_values, 1)


def lines(svg: str) -> dict[str, np.ndarray]:
    """legend value -> ``(points, 2)`` pixel coordinates of each line mark, sorted by x."""
    found = {}
    for mark in re.findall(r'<path[^>]*aria-roledescription="line mark"[^>]*>', svg):
        name = re.search(r"; (\w+): ([^;\"]+)\"", mark)
        path = re.search(r' d="([^"]+)"', mark).group(1)
        start = re.match(r"M([-\d.]+),([-\d.]+)", path)
        points = [(float(start.group(1)), float(start.group(2)))]
        for segment in re.findall(r"[CL]([^CLMZ]+)", path):
            numbers = [float(n) for n in re.findall(r"-?[\d.]+", segment)]
            points.append((numbers[-2], numbers[-1]))
        found[f"{name.group(1)} {name.group(2)}" if name else str(len(found))] = np.array(sorted(points))
    return found


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    parser.add_argument("svg", type=Path)
    parser.add_argument("--at", type=float, nargs="+", default=[1.0], help="x values (millions of env steps)")
    args = parser.parse_args()
    svg = args.svg.read_text()
    fit_x, fit_y = axis_fits(svg)
    for name, points in lines(svg).items():
        x, y = np.polyval(fit_x, points[:, 0]), np.polyval(fit_y, points[:, 1])
        values = ", ".join(f"{at:g}M: {100 * np.interp(at, x, y):.1f}%" for at in args.at)
        print(f"{name}: {values}")


if __name__ == "__main__":
    main()
