"""Options shared by the commands that compose: one --n limit for compose, compare and match (before
this, compare and match accepted --n 100000 and ran out of memory)."""

import pytest
from click.testing import CliRunner

from flakedb.cli.main import cli


@pytest.mark.parametrize("command", ["compose", "compare", "match"])
@pytest.mark.parametrize("n", ["100000", "7", "0"])
def test_node_count_is_refused_before_any_work(command, n, tmp_path):
    recipe = tmp_path / "r.yaml"
    recipe.write_text("not even read\n")
    args = [command, str(recipe), "--n", n]
    if command == "match":
        args += ["--target", str(tmp_path / "t.csv"), "--out", str(tmp_path / "o")]
    r = CliRunner().invoke(cli, args)
    assert r.exit_code == 2, r.output
    assert f"--n {n}: the node count must be even, 8 ≤ n ≤ 512" in r.output
    assert not (tmp_path / "o").exists()
