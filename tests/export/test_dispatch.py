"""The export commands dispatch through the export registry (issue #34: EXPORT_METHODS was read only by tests, so
its docstring's "export commands name routes by these keys" was untrue and a route could change in one place
only).  A route replaced in the registry must be what the command runs."""

from pathlib import Path

import pytest
from click.testing import CliRunner

from flakedb.cli.main import cli
from flakedb.export import registry


@pytest.mark.parametrize("args, method", [
    (["export-openpbr", "{src}", "--out", "{out}"], "openpbr"),
    (["export-cpa", "{src}", "--out", "{out}"], "cpa"),
    (["export-mitsuba", "{src}", "--out", "{out}/p.measured.tensor"], "mitsuba-coated"),
    (["export-mitsuba", "{src}", "--no-coat", "--out", "{out}/p.measured.tensor"], "mitsuba-measured"),
])
def test_export_commands_run_the_registrys_route(tmp_path, monkeypatch, args, method):
    src = tmp_path / "p.bsdf"
    src.write_bytes(b"never read: the route is replaced")
    seen = []

    class Stop(Exception):
        pass

    def spy(s, out, **kw):
        seen.append((Path(s), kw))
        raise Stop

    monkeypatch.setitem(registry.EXPORT_METHODS, method, (spy,) + registry.EXPORT_METHODS[method][1:])
    r = CliRunner().invoke(cli, [a.format(src=src, out=tmp_path / "out") for a in args])
    assert seen and seen[0][0] == src, r.output
    assert r.exit_code != 0                         # the spy stopped it: nothing else ran the export
