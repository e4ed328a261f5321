"""Where a benchmark writes: a try-out never overwrites the committed figures."""

from __future__ import annotations

from pathlib import Path

from bench import bandwidth


def test_a_quick_or_redirected_bandwidth_run_never_writes_the_committed_figures(
    tmp_path: Path,
) -> None:
    committed_json, committed_plots = bandwidth.output_paths(quick=False, json_path=None)
    assert committed_json.name == "bandwidth.json" and committed_plots.name == "plots"
    for quick, given in (
        (True, None),
        (True, str(tmp_path / "b.json")),
        (False, str(tmp_path / "b.json")),
    ):
        path, plots = bandwidth.output_paths(quick=quick, json_path=given)
        assert path != committed_json and plots != committed_plots, (quick, given)
    assert (
        bandwidth.output_paths(quick=False, json_path=str(tmp_path / "b.json"))[1]
        == tmp_path / "plots"
    )
