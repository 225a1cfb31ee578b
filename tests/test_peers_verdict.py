"""``benchmarks.peers``' verdicts: the issue's rule (no slower, at equal or better
accuracy) applied to each (setting, peer) pair and each scene, as its report states it."""

from benchmarks import peers


def cell(ms, failed=0, **errors):
    return {"ms": ms, "failed": failed, **errors}


def test_verdict_needs_both_time_and_every_error():
    jax = cell(2.0, angle_deg=0.01, center_rel=0.001)
    assert peers.verdict(jax, cell(2.0, angle_deg=0.01, center_rel=0.001)) == "ahead"
    assert peers.verdict(jax, cell(3.0, angle_deg=0.02, center_rel=0.002)) == "ahead"
    # one error worse is enough to be less accurate
    assert peers.verdict(jax, cell(3.0, angle_deg=0.02, center_rel=0.0005)) == \
        "faster, less accurate"
    assert peers.verdict(jax, cell(1.0, angle_deg=0.02, center_rel=0.002)) == \
        "slower, more accurate"
    assert peers.verdict(jax, cell(1.0, angle_deg=0.005, center_rel=0.002)) == "behind"


def test_a_failing_side_is_judged_by_its_failures():
    ok = cell(2.0, angle_deg=0.01)
    # a peer that found nothing on some cloud: no time to the same answer
    assert peers.verdict(ok, cell(1.0, failed=1)) == "peer failed"
    # ... unless jaxfit is ahead on its own terms anyway
    assert peers.verdict(ok, cell(3.0, failed=1, angle_deg=0.02)) == "ahead"
    # jaxfit failing is never at equal accuracy, and both failing is no excuse either
    assert peers.verdict(cell(1.0, failed=1, angle_deg=0.01), cell(2.0, angle_deg=0.5)) == \
        "faster, less accurate"
    assert peers.verdict(cell(3.0, failed=1), cell(2.0, failed=1)) == "behind"


def test_verdicts_count_every_pair_and_list_the_others():
    rows = [{"shape": "plane", "points": 1000, "outliers": 0.3, "methods": {
        "jaxfit": cell(2.0, angle_deg=0.01),
        "open3d_default": {**cell(1.0, angle_deg=0.02), "ratio": 2.0},
        "cgal": {**cell(4.0, angle_deg=0.05), "ratio": 0.5}}}]
    scenes = [{"scene": "s", "methods": {"jaxfit": {"s": 0.2, "found": 5},
                                         "cgal": {"s": 0.1, "found": 3}}},
              {"scene": "t", "methods": {"jaxfit": {"s": 0.1, "found": 5},
                                         "cgal": {"s": 0.1, "found": 5}}}]
    summary = peers.verdicts(rows, scenes)
    assert summary["single_pairs"] == 2
    assert summary["single"]["ahead"] == 1 and summary["single"]["slower, more accurate"] == 1
    assert summary["single_not_ahead"] == [
        ("plane 1000 30 % vs Open3D default", "slower, more accurate", 2.0)]
    assert summary["scenes"] == {"ahead": 1, "slower": 1, "finds fewer": 0, "behind": 0}
    text = "\n".join(peers.verdict_markdown(summary))
    assert "ahead 1, slower, more accurate 1" in text and "s: slower (2.00x" in text


def test_a_run_without_peers_says_so():
    rows = [{"shape": "plane", "points": 1000, "outliers": 0.3,
             "methods": {"jaxfit": cell(2.0, angle_deg=0.01)}}]
    summary = peers.verdicts(rows, [{"scene": "s", "methods": {"jaxfit": {"s": 0.2,
                                                                         "found": 5}}}])
    assert summary["single_pairs"] == 0 and summary["scene_count"] == 0
    assert any(line.startswith("No peer imported") for line in peers.verdict_markdown(summary))


def test_looped_times_each_method_back_to_back_and_judges_by_those_times():
    calls = []

    def method(name, seconds):
        def setup(points, shape, threshold, seed):
            def run():
                calls.append(name)
                end = peers.time.perf_counter() + seconds
                while peers.time.perf_counter() < end:
                    pass
            return run, None
        return setup

    methods = {"jaxfit": method("jaxfit", 0.0002), "cgal": method("cgal", 0.0004),
               "open3d_1000": method("open3d_1000", 0.09)}  # too slow to loop
    rows = [{"shape": "plane", "points": 1000, "outliers": 0.3, "methods": {
        "jaxfit": cell(5.0, angle_deg=0.01), "cgal": {**cell(1.0, angle_deg=0.02),
                                                       "ratio": 5.0},
        "open3d_1000": {**cell(90.0, angle_deg=0.02), "ratio": 0.05}}},
            {"shape": "plane", "points": 100_000, "outliers": 0.3,
             "methods": {"jaxfit": cell(5.0, angle_deg=0.01)}}]
    peers.looped(rows, methods, calls=4, turns=2)
    j, c = rows[0]["methods"]["jaxfit"], rows[0]["methods"]["cgal"]
    assert 0.15 < j["loop_ms"] < c["loop_ms"] and "loop_ms" not in rows[0]["methods"]["open3d_1000"]
    assert "loop_ms" not in rows[1]["methods"]["jaxfit"]  # (over LOOP_MAX_POINTS)
    # per turn: one untimed and 4 timed calls back to back, each method in turn
    assert calls.count("cgal") == 2 * 5 and "open3d_1000" not in calls
    assert calls[-10:] == ["jaxfit"] * 5 + ["cgal"] * 5
    assert c["loop_ratio"] == j["loop_ms"] / c["loop_ms"] < 1
    # judged by the loop's times: ahead, where the interleaved times say slower
    loop = peers.verdicts(rows, [], timed="loop_ms")
    assert loop["single_pairs"] == 1 and loop["single"]["ahead"] == 1
    assert peers.verdicts(rows, [])["single"]["slower, more accurate"] == 1
    text = "\n".join(peers.loop_markdown(rows))
    assert "ahead 1 (the same pairs by the table's times: slower, more accurate 1)" in text
    table = text[text.index("| shape"):]
    assert "| plane | 1000 | 30 % |" in table and "100000" not in table
    assert "CGAL" in table and "Open3D 1000 it" not in table  # (no peer looped: no column)
