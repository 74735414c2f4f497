"""The multi-angle figure of `compare --plot` (flakedb.render.plots) and the target's label (issue 39 item 6).

Guards against: curve colours that repeat (45as-15 and 15as80 were the same blue: a cycle of ten colours for
eleven geometries), a*b* angle labels printed over each other ("1525"), target points that are neither joined
nor named, and a target CSV without a ``# name:`` line labelled by its folder path.
"""

import itertools
import re

import colour
import numpy as np
import pytest
import yaml
from click.testing import CliRunner

from flakedb.cli.main import cli
from flakedb.colour.settings import E2539_GEOMETRIES
from flakedb.match.targets import Target, read_target, write_target
from flakedb.render.plots import geometry_colours, multiangle_figure, place_labels
from tests.render.pdf_text import pdf_texts

G = np.asarray(E2539_GEOMETRIES, float)
WL = np.arange(400.0, 701.0, 20.0)


def _lab_crowded():
    """A pearl-like travel whose 45° and 15° points crowd together in a*b* (the labels' worst case)."""
    asp = G[:, 1]
    return np.stack([60.0 - 0.3 * asp, 2.0 + 0.02 * asp, 10.0 - 0.05 * asp], axis=-1)


def _min_de00(rgb):
    lab = colour.XYZ_to_Lab(colour.sRGB_to_XYZ(np.asarray(rgb, float)))
    d = colour.delta_E(lab[:, None], lab[None], method="CIE 2000")
    return float(np.min(d[~np.eye(len(rgb), dtype=bool)]))


@pytest.mark.parametrize("count", [2, 6, 11, 12])
def test_geometry_colours_are_distinct(count):
    """Every pair of curve colours at least 10 ΔE00 apart (two neighbours in a cycle of ten: 0)."""
    assert _min_de00(geometry_colours(count)) >= 10.0


def test_spectra_curves_have_one_colour_per_geometry():
    lab = _lab_crowded()
    R = np.array([0.2 + 0.1 * np.sin(WL / 50.0 + k) for k in range(len(G))])
    fig = multiangle_figure(G, lab, lab + 1.0, WL, R, 0.9 * R, title="r", target_name="A-17")
    ax = next(a for a in fig.axes if a.get_xlabel() == "wavelength (nm)")
    solid = [line for line in ax.get_lines() if line.get_linestyle() == "-"]
    labels = [line.get_label() for line in solid]
    assert labels == [f"{i:g}as{a:g}" for i, a in G]
    rgb = np.array([colour_to_rgb(line.get_color()) for line in solid])
    assert _min_de00(rgb) >= 10.0
    i, j = labels.index("45as-15"), labels.index("15as80")
    assert not np.allclose(rgb[i], rgb[j])
    dashed = [line for line in ax.get_lines() if line.get_linestyle() == "--"]   # each target curve in its colour
    assert [colour_to_rgb(line.get_color()) for line in dashed] == [tuple(c) for c in rgb]


def colour_to_rgb(c):
    from matplotlib.colors import to_rgb

    return tuple(to_rgb(c))


def _boxes(ax):
    renderer = ax.figure.canvas.get_renderer()
    return [t.get_window_extent(renderer) for t in ax.texts]


def _overlaps(boxes):
    return [(a, b) for a, b in itertools.combinations(range(len(boxes)), 2)
            if min(boxes[a].x1, boxes[b].x1) > max(boxes[a].x0, boxes[b].x0)
            and min(boxes[a].y1, boxes[b].y1) > max(boxes[a].y0, boxes[b].y0)]


def test_travel_labels_do_not_overlap():
    """Every predicted and target point of the a*b* travel labelled, and no two label boxes overlap as the
    renderer measures them (after the last draw).  The same labels at one fixed offset (the old layout) do
    overlap on these points: the test can fail."""
    lab = _lab_crowded()
    fig = multiangle_figure(G, lab, lab + [0.0, 0.4, 0.6], title="r", target_name="A-17")
    ax = next(a for a in fig.axes if a.get_xlabel() == "a*")
    fig.canvas.draw()
    texts = [t.get_text() for t in ax.texts]
    assert sorted(texts) == sorted([f"{i:g}as{a:g}" for i, a in G] * 2)
    assert not _overlaps(_boxes(ax))
    assert not _overlaps(_boxes(ax) + [ax.get_legend().get_window_extent(fig.canvas.get_renderer())])
    for t in list(ax.texts):
        t.remove()
    for (a, b), (il, asp) in zip(lab[:, 1:], G):
        ax.annotate(f"{il:g}as{asp:g}", (a, b), fontsize=6, xytext=(3, 3), textcoords="offset points")
    fig.canvas.draw()
    assert _overlaps(_boxes(ax))


def test_place_labels_alone_avoids_markers_and_labels():
    from matplotlib.backends.backend_agg import FigureCanvasAgg
    from matplotlib.figure import Figure

    fig = Figure(figsize=(3, 3))
    FigureCanvasAgg(fig)
    ax = fig.add_subplot()
    xy = np.array([[0.0, 0.0], [0.02, 0.01], [0.04, 0.0], [0.01, 0.03], [1.0, 1.0]])
    ax.plot(xy[:, 0], xy[:, 1], "o")
    ax.set(xlim=(-0.5, 1.5), ylim=(-0.5, 1.5))
    fig.draw_without_rendering()
    anns = place_labels(ax, xy, ["alpha", "beta", "gamma", "delta", "far"])
    fig.canvas.draw()
    assert len(anns) == 5 and not _overlaps(_boxes(ax))


def test_target_points_joined_and_named():
    lab = _lab_crowded()
    lt = lab + [1.0, 0.5, -0.5]
    fig = multiangle_figure(G, lab, lt, title="r", target_name="A-17")
    ax_L = next(a for a in fig.axes if a.get_ylabel() == "L*")
    for il in (45.0, 15.0):
        line = next(ln for ln in ax_L.get_lines() if ln.get_label() == f"A-17, {il:g}° illum.")
        assert line.get_linestyle() == "--" and line.get_marker() == "s"       # joined, open squares
        sel = np.flatnonzero(G[:, 0] == il)
        sel = sel[np.argsort(G[sel, 1])]
        np.testing.assert_array_equal(line.get_xdata(), G[sel, 1])
        np.testing.assert_array_equal(line.get_ydata(), lt[sel, 0])
    legend = [t.get_text() for t in ax_L.get_legend().get_texts()]
    assert "A-17, 45° illum." in legend and "A-17, 15° illum." in legend


def test_target_label_is_its_name_else_its_file_stem():
    assert Target(G, source="/lab/2026/panels/A-17.csv").label == "A-17"
    assert Target(G, source="/lab/2026/panels/A-17.csv", name="Panel A").label == "Panel A"


@pytest.mark.slow
def test_compare_names_a_nameless_target_by_its_stem(tmp_path):
    """`compare --table --plot` (PDF) with a target CSV that has no ``# name:`` line in a nested folder: the
    table's target column and the figure's texts say its stem, never the folder path."""
    from flakedb.match.fit import predict, recipe_from_doc
    from tests.match.test_fit import _text

    doc = yaml.safe_load(_text(VF_METALLIC=0.04, VF_YELLOW=0.02))
    (tmp_path / "r.yaml").write_text(yaml.safe_dump(doc))
    folder = tmp_path / "lab" / "2026" / "panels"
    folder.mkdir(parents=True)
    pred = predict(recipe_from_doc(yaml.safe_load(_text(VF_METALLIC=0.04, VF_YELLOW=0.025))), G[:6])
    write_target(folder / "A-17.csv", pred.geometries, reflectance=pred.rf, wavelength_nm=pred.wavelength_nm)
    assert read_target(folder / "A-17.csv").name == ""
    r = CliRunner().invoke(cli, ["compare", str(tmp_path / "r.yaml"), "--target", str(folder / "A-17.csv"),
                                 "--table", str(tmp_path / "t.csv"), "--plot", str(tmp_path / "figs"),
                                 "--plot-format", "pdf"])
    assert r.exit_code in (0, 1), r.output
    rows = (tmp_path / "t.csv").read_text().splitlines()[1:]
    assert rows and all(row.split(",")[1] == "A-17" for row in rows)
    texts = pdf_texts((tmp_path / "figs" / "two-species--A-17.pdf").read_bytes())
    joined = "\n".join(texts)
    assert "two-species vs A-17" in joined and "A-17, 45° illum." in joined
    assert not re.search(r"panels|2026", joined), [t for t in texts if "panels" in t]
