"""Batches, tables, DataFrames and plots (flakedb.match.batch, `compare` with many recipes/targets, --plot).

Guards against: a batch that pairs a recipe with the wrong target's numbers (each recipe is composed
once and sliced per target), rows lost or duplicated in the table, a DataFrame that differs from the
table, a --pairs list read as all pairs, and a figure that does not open or does not show the target.
"""

import csv

import numpy as np
import pytest
import yaml
from click.testing import CliRunner

from flakedb.cli.main import cli
from flakedb.match import batch
from flakedb.match.fit import predict, recipe_from_doc
from flakedb.match.targets import E2194_GEOMETRIES, read_target, write_target
from flakedb.paint.catalog import load_catalog
from tests.match.test_fit import _text

YELLOW = [0.004, 0.006, 0.009, 0.013, 0.02, 0.03, 0.045, 0.065, 0.09, 0.12]


@pytest.fixture(scope="module")
def ladder(tmp_path_factory):
    """10 recipes (yellow loading steps) and, as targets, their own predictions (spectral, E2194)."""
    d = tmp_path_factory.mktemp("batch")
    (d / "recipes").mkdir()
    (d / "targets").mkdir()
    cat = load_catalog(None)
    for k, vf in enumerate(YELLOW):
        doc = yaml.safe_load(_text(VF_METALLIC=0.04, VF_YELLOW=vf))
        doc["name"] = f"r{k:02d}"
        (d / "recipes" / f"r{k:02d}.yaml").write_text(yaml.safe_dump(doc))
        pr = predict(recipe_from_doc(doc, catalog=cat), E2194_GEOMETRIES, catalog=cat)
        write_target(d / "targets" / f"t{k:02d}.csv", pr.geometries, reflectance=pr.rf, wavelength_nm=pr.wavelength_nm,
                     name=f"t{k:02d}")
    return d


def test_ten_recipes_against_ten_targets_in_one_command(ladder, tmp_path):
    """The issue's done-when: one command, 10 × 10 pairs, one table.  Each recipe matches its own target
    (ΔE00 < 1e-6) and no other (the loadings differ by ≥ 1.4×), so exactly the diagonal passes."""
    table = tmp_path / "table.csv"
    r = CliRunner().invoke(cli, ["compare", str(ladder / "recipes"), "--target", str(ladder / "targets"),
                                 "--table", str(table)])
    assert r.exit_code == 1, r.output                              # the off-diagonal pairs fail
    assert "10 of 100 pair(s) pass" in r.output, r.output
    rows = list(csv.DictReader(table.open()))
    assert len(rows) == 100 * len(E2194_GEOMETRIES)
    for row in rows:
        same = row["recipe"][1:] == row["target"][1:]
        assert (row["passed"] == "True") == same, row
        if same:
            assert float(row["dE00"]) < 1e-3
    # the listed pairs only: the diagonal, all pass
    pairs = tmp_path / "pairs.csv"
    pairs.write_text("recipe,target\n" + "".join(f"{ladder}/recipes/r{k:02d}.yaml,{ladder}/targets/t{k:02d}.csv\n"
                                                 for k in range(10)))
    r = CliRunner().invoke(cli, ["compare", "--pairs", str(pairs)])
    assert r.exit_code == 0 and "10 of 10 pair(s) pass" in r.output, r.output


def test_dataframe_equals_the_table(ladder):
    pd = pytest.importorskip("pandas")
    cat = load_catalog(None)
    from flakedb.paint.recipe import load_recipe

    recs = [load_recipe(ladder / "recipes" / f"r{k:02d}.yaml", cat) for k in (0, 5)]
    tgts = [read_target(ladder / "targets" / f"t{k:02d}.csv") for k in (0, 5, 9)]
    t9 = tgts[2]                                   # a target with fewer geometries, in another order
    keep = [4, 0, 2]
    tgts[2] = type(t9)(geometries=t9.geometries[keep], reflectance=t9.reflectance[keep],
                       wavelength_nm=t9.wavelength_nm, observer=t9.observer, illuminant=t9.illuminant, name="t09")
    comps = batch.compare_batch(recs, tgts, catalog=cat)
    df = batch.to_dataframe(comps)
    assert isinstance(df, pd.DataFrame) and df.shape == (2 * (6 + 6 + 3), len(batch.LONG_COLUMNS))
    rows = batch.long_rows(comps)
    np.testing.assert_array_equal(df["dE00"].to_numpy(), [r["dE00"] for r in rows])
    s = batch.to_dataframe(comps, summary=True).set_index(["recipe", "target"])
    assert s.loc[("r00", "t00"), "max_dE00"] < 1e-3 and s.loc[("r05", "t00"), "max_dE00"] > 1.0
    # the batch's numbers are the single comparison's: r05 vs t09 by hand
    lab = predict(recs[1], tgts[2].geometries, catalog=cat).lab(tgts[2].observer, tgts[2].illuminant)
    np.testing.assert_allclose(df[(df.recipe == "r05") & (df.target == "t09")][["L", "a", "b"]].to_numpy(), lab,
                               atol=1e-9)


def test_plots_open_and_show_the_target(ladder, tmp_path):
    """--plot writes a PNG per comparison that decodes; with the target drawn it differs from the same
    figure without it (the target markers are there); PDF by suffix; an unknown suffix is refused."""
    import matplotlib.image as mpimg

    from flakedb.render.plots import plot_multiangle

    r = CliRunner().invoke(cli, ["compare", str(ladder / "recipes" / "r03.yaml"), "--target",
                                 str(ladder / "targets" / "t04.csv"), "--plot", str(tmp_path / "fig")])
    assert r.exit_code == 1, r.output
    png = tmp_path / "fig" / "r03--t04.png"
    img = mpimg.imread(png)
    assert img.ndim == 3 and img.shape[0] > 500 and img.shape[1] > 1000
    t = read_target(ladder / "targets" / "t04.csv")
    lab_t = t.lab_under()
    g = t.geometries
    a = plot_multiangle(tmp_path / "a.png", g, lab_t + 2.0, lab_t, t.wavelength_nm, t.reflectance * 0.9, t.reflectance)
    b = plot_multiangle(tmp_path / "b.png", g, lab_t + 2.0, None, t.wavelength_nm, t.reflectance * 0.9)
    assert not np.array_equal(mpimg.imread(a), mpimg.imread(b))
    assert plot_multiangle(tmp_path / "c.pdf", g, lab_t).read_bytes().startswith(b"%PDF")
    with pytest.raises(ValueError, match="by the file's suffix"):
        plot_multiangle(tmp_path / "c.gif", g, lab_t)
    assert not list(tmp_path.glob(".*"))                           # no temporary leftovers
