"""``benchmarks.decomposition --keys``: which meshes it runs, and the table it writes
for those it leaves out (no decomposition runs here)."""

import json

from benchmarks import decomposition as bench


def test_key_spread_leaves_out_meshes_without_a_well_defined_solid(tmp_path, monkeypatch):
    monkeypatch.setattr(bench, "RESULTS", tmp_path)
    (tmp_path / "graspit_mug").mkdir()
    (tmp_path / "graspit_mug" / "vs_coacd.json").write_text(json.dumps(
        {"coacd": {"viou": bench.WELL_DEFINED - 0.1, "chamfer": 0.02},
         "jaxfit": {"parts": 2}}))
    bench.key_spread(["graspit_mug", "graspit_phone"], 2)
    table = (tmp_path / "keys.md").read_text()
    assert "graspit_mug (hulls' vIoU 0.500: not well defined)" in table
    assert "graspit_phone (no vs_coacd.json" in table
    written = json.loads((tmp_path / "keys.json").read_text())
    assert written["keys"] == 2 and written["runs"] == {}
