"""Issue 49: what the benchmark gives after its runs. Figures that cannot crash or hang a run
(drawn from what the runs recorded), exit codes that say what happened, a console table that
fits the terminal, figures a reader can read (checked on the artist tree), help for every
option. The benchmarks here are tiny: 15 s of BB's path at 10-20 particles (seed 0 at clutter
level 2 fails after ~5 s with 20 particles, seed 1 runs to the end).
"""

import io
import itertools
import json
import os
import subprocess
import sys
import time
from pathlib import Path

import numpy as np
import pytest

from slam_gym.cli import main
from slam_gym.commands.runs import EXIT_RUN_ERRORS
from slam_gym.evaluation import read_results

REPO = Path(__file__).resolve().parents[2]
TINY = ["--clutter-levels", "2", "--particles", "20", "--n-steps", "150", "--baselines", "",
        "--quiet"]
SEVEN_FIGURES = ("success_rates.png", "pareto.png", "pareto_interface.png",
                 "uncertainty_traces.png", "nees.png", "decisions.png", "map.png")

FAILING = '''
import time

import numpy as np


class Raiser:
    """Raises on world 0 (the figure world), fuses every decision elsewhere."""

    def reset(self):
        pass

    def act(self, obs, info):
        if info["world_seed"] == 0:
            raise RuntimeError("my policy broke on world 0")
        return np.array([1, 0], dtype=np.int64)


class Hang:
    """Never returns on world 0."""

    def reset(self):
        pass

    def act(self, obs, info):
        if info["world_seed"] == 0:
            while True:
                time.sleep(1.0)
        return np.array([1, 1], dtype=np.int64)


class AlwaysRaises:
    def reset(self):
        pass

    def act(self, obs, info):
        raise KeyError("speed")
'''


@pytest.fixture
def user_dir(tmp_path, monkeypatch):
    folder = tmp_path / "user"
    folder.mkdir()
    (folder / "failing_rules.py").write_text(FAILING)
    sys.modules.pop("failing_rules", None)
    monkeypatch.syspath_prepend(str(folder))
    return folder


def run_cli(args, user_dir, timeout_s, columns=None):
    """``slam-gym ARGS`` in a new process, its output piped (as through ``| cat``)."""
    env = {k: v for k, v in os.environ.items() if k != "COLUMNS"}
    env["PYTHONPATH"] = os.pathsep.join([str(REPO), str(user_dir), env.get("PYTHONPATH", "")])
    if columns is not None:
        env["COLUMNS"] = str(columns)
    return subprocess.run([sys.executable, "-m", "slam_gym.cli", *args], cwd=REPO, env=env,
                          capture_output=True, text=True, timeout=timeout_s)


def test_a_raising_and_a_hanging_policy_with_figures_end_with_exit_3_the_table_and_figures(
        user_dir, tmp_path):
    """The issue's probes, figures on: a policy that raises on the figure world and one that
    never returns there (stopped by --run-timeout-s). The benchmark ends (the test has its own
    limit), exits 3 with one summary line after the table, writes all seven figures, drawn
    from the other policy's run, and does the same when run again (resumed)."""
    out = tmp_path / "out"
    # the limit leaves the first run of a fresh process time to load the compiled filters on a
    # busy machine (else the raising run could time out before it raises)
    args = ["benchmark", "--policies", "failing_rules:Raiser,failing_rules:Hang,fixed-10s",
            "--seeds", "2", *TINY, "--executor", "serial", "--run-timeout-s", "15",
            "--out", str(out)]
    for attempt in range(2):
        t0 = time.monotonic()
        done = run_cli(args, user_dir, timeout_s=240)
        assert done.returncode == EXIT_RUN_ERRORS, done.stderr[-3000:]
        assert "Traceback" not in done.stderr
        summary = [line for line in done.stderr.splitlines() if "runs failed" in line]
        assert len(summary) == 1 and summary[0].startswith("slam-gym benchmark: 2 of 6 runs")
        assert "RuntimeError: my policy broke on world 0" in summary[0]
        for name in ("failing_rules:Raiser", "failing_rules:Hang", "fixed-10s"):
            assert name in done.stdout
        assert "wrote" in done.stdout and "7 figures" in done.stdout
        assert all((out / name).stat().st_size > 5_000 for name in SEVEN_FIGURES)
        if attempt == 1:  # resumed: nothing ran, nothing replayed
            assert time.monotonic() - t0 < 60
    rows = {(r["policy"], r["seed"]): r for r in read_results(out)}
    assert rows[("failing_rules:Raiser", 0)]["status"] == "error"
    assert "per-run limit of 15 s" in rows[("failing_rules:Hang", 0)]["error"]
    assert rows[("failing_rules:Hang", 1)]["status"] == "ok"
    assert len(list((out / "episodes").glob("*.npz"))) == 1  # fixed-10s's run of world 0


def test_figures_leave_out_a_failed_policy_and_say_so(user_dir, tmp_path):
    """The Python API: figure errors and notes, never an exception after the runs."""
    import failing_rules

    import policies
    from slam_gym.evaluation import benchmark
    from slam_gym.evaluation.episodes import episode_path, read_episode

    # level 0: fixed-10s survives both worlds there, so every figure has something to draw
    result = benchmark({"raiser": failing_rules.Raiser, "fixed-10s": policies.make("fixed-10s")},
                       clutter_levels=[0], seeds=2, env_kwargs={"n_particles": 20, "n_steps": 150},
                       baselines=[],
                       executor="serial", out=tmp_path / "out")
    assert set(result.figures) == {"success", "pareto", "pareto_interface", "uncertainty",
                                   "nees", "decisions", "map"}
    assert result.figure_errors == {}
    ok = next(r for r in result.rows if r["policy"] == "fixed-10s" and r["seed"] == 0)
    recording = read_episode(episode_path(result.out, ok["key"]))
    # the recording is the run the table counts
    assert recording["n_fusions"] == ok["n_fusions"] == int(recording["fused"].sum())
    assert len(recording["nees"]) == ok["iterations"]
    assert recording["failed"] == (not ok["success"])


def test_a_benchmark_whose_every_run_failed_exits_3_with_the_one_line_summary(user_dir,
                                                                              tmp_path, capsys):
    out = tmp_path / "out"
    code = main(["benchmark", "--policies", "failing_rules:AlwaysRaises", "--seeds", "2", *TINY,
                 "--executor", "serial", "--out", str(out)])
    assert code == EXIT_RUN_ERRORS
    captured = capsys.readouterr()
    assert "no group" not in captured.err
    assert captured.err.strip().splitlines()[-1].startswith(
        "slam-gym benchmark: 2 of 2 runs failed")
    assert "failing_rules:AlwaysRaises" in captured.out  # the table
    assert json.loads((out / "summary.json").read_text())["n_errors"] == 2


# ---------------------------------------------------------------------------------------------
# The console table


def table_parts(text: str) -> list[tuple[list[str], list[list[str]]]]:
    """The parts of a printed rich table: (headers, rows of cells), from its box characters."""
    parts, header_lines, rows, state = [], [], [], None
    for line in text.splitlines():
        if line.startswith("┏"):
            header_lines, rows, state = [], [], "header"
        elif line.startswith("┡"):
            state = "body"
        elif line.startswith("└"):
            columns = zip(*([c.strip() for c in h.split("┃")[1:-1]] for h in header_lines),
                          strict=True)
            parts.append((  # a header folded over lines is joined back
                [" ".join(p for p in pieces if p) for pieces in columns], rows))
            state = None
        elif state == "header" and line.startswith("┃"):
            header_lines.append(line)
        elif state == "body" and line.startswith("│"):
            cells = [c.strip() for c in line.split("│")[1:-1]]
            if cells[0] or not rows:
                rows.append(cells)
            else:  # a cell wrapped at a space goes on below; the names never wrap
                rows[-1] = [" ".join(p for p in pair if p) for pair in zip(rows[-1], cells,
                                                                          strict=True)]
    return parts


def check_table(text: str, doc, width: int) -> None:
    """Every line within ``width``; every cell of every row whole on its row's line, under
    its whole header, in some part."""
    from slam_gym.evaluation.summary import table_cells

    lines = [line for line in text.splitlines() if line[:1] in "┏┃┡│└"]
    assert lines and max(map(len, lines)) <= width, max(map(len, lines))
    header, body = table_cells(doc)
    parts = table_parts(text)
    assert parts, text
    seen = set()
    for headers, rows in parts:
        assert len(rows) == len(body)
        columns = [header.index(h) for h in headers]  # a cut header would not be found
        seen.update(columns)
        for row, cells in zip(body, rows, strict=True):
            assert cells == [row[i] for i in columns]
    assert seen == set(range(len(header)))


def test_the_quick_benchmarks_table_fits_80_columns_and_a_pipe_with_no_value_cut(
        tmp_path, capsys, monkeypatch):
    """--quick (its policies and levels; one tiny world each): in an 80-column terminal
    (COLUMNS) and piped through another process (100 columns), every value whole."""
    out = tmp_path / "quick"
    quick = ["benchmark", "--quick", "--seeds", "1", "--particles", "10", "--n-steps", "150",
             "--executor", "serial", "--no-figures", "--quiet", "--out", str(out)]
    monkeypatch.setenv("COLUMNS", "80")
    assert main(quick) == 0
    doc = json.loads((out / "summary.json").read_text())
    printed = capsys.readouterr().out
    check_table(printed, doc, 80)
    assert len(table_parts(printed)) > 1  # 14 columns do not fit 80: split, not cut
    assert "-" in "".join(r[-1] for _, rows in table_parts(printed) for r in rows)  # returns
    piped = run_cli(quick, tmp_path, timeout_s=120)  # no COLUMNS, piped; resumed: no run
    assert piped.returncode == 0, piped.stderr[-2000:]
    check_table(piped.stdout, doc, 100)
    markdown = (out / "table.md").read_text()
    assert max(len(line) for line in markdown.splitlines()) > 160  # table.md stays whole


def test_a_split_table_repeats_the_names_and_keeps_long_names_whole():
    from rich.console import Console

    from slam_gym.evaluation.summary import format_tables, split_columns

    header = ["system/policy", "clutter", "a long header of words", "x"]
    body = [["a_long_package.its_rules_module:ReturnsNone", "2", "-2069 (– / -2069)", "1"]]
    for width in (60, 80, 200):
        parts = split_columns(header, body, width)
        assert all([i for i, _ in part][:2] == [0, 1] for part in parts)
        assert sorted({i for part in parts for i, _ in part}) == [0, 1, 2, 3]
        assert all(w >= max(map(len, body[0][i].split())) for part in parts for i, w in part)
        if width >= 80:  # room for every cell on one line
            assert all(w >= len(body[0][i]) for part in parts for i, w in part)
    doc = [{"policy": body[0][0], "scenario": "s", "clutter_level": 2, "options": {}, "n": 1,
            "n_errors": 0, "success_rate": 1.0, "success_ci95": [0.2, 1.0], "return": -2069.0,
            "return_succeeded": -2069.0, "return_failed": None}]
    console = Console(width=70, record=True, file=io.StringIO())
    for table in format_tables(doc, width=70, title="t"):
        console.print(table, width=max(70, table.min_width), crop=False)
    # 'optimisations' cannot fold beside the 43-character name: that part takes 73 columns
    check_table(console.export_text(), doc, 73)


# ---------------------------------------------------------------------------------------------
# Help


def all_actions():
    import argparse

    from slam_gym.cli import build_parser

    def walk(parser, path):
        for action in parser._actions:
            if isinstance(action, argparse._SubParsersAction):
                for name, sub in action.choices.items():
                    yield from walk(sub, [*path, name])
            elif not isinstance(action, argparse._HelpAction):
                yield " ".join(path), action

    return list(walk(build_parser(), []))


def test_every_option_of_every_command_has_help_text():
    missing = [f"{command} {action.option_strings or action.dest}"
               for command, action in all_actions() if not (action.help or "").strip()]
    assert not missing, missing
    seeds = {command: action.metavar for command, action in all_actions()
             if "--seeds" in action.option_strings and action.type is int}
    assert seeds and set(seeds.values()) == {"N"}, seeds


def test_argparse_errors_are_one_line(capsys):
    with pytest.raises(SystemExit) as exc:
        main(["benchmark", "--particles", "many"])
    assert exc.value.code == 2
    lines = capsys.readouterr().err.strip().splitlines()
    assert len(lines) == 1 and "--particles" in lines[0] and "--help" in lines[0]


def test_fingerprint_of_a_file_that_is_not_a_zip_says_so(tmp_path, capsys):
    model = tmp_path / "model.zip"
    model.write_text("not a zip")
    assert main(["fingerprint", str(model)]) == 2
    err = capsys.readouterr().err.strip()
    assert "is not a zip file" in err and "config JSON" not in err.split("(")[0]


# ---------------------------------------------------------------------------------------------
# Figures, read from their artist trees


def visible_texts(fig):
    """Every non-empty text drawn on ``fig``, with its box in pixels (tick labels only of the
    ticks inside the view)."""
    from matplotlib.text import Annotation

    fig.canvas.draw()
    renderer = fig.canvas.get_renderer()
    texts = list(fig.texts)
    for text in (fig._supxlabel, fig._supylabel, fig._suptitle):
        if text is not None:
            texts.append(text)
    for legend in [*fig.legends, *(ax.get_legend() for ax in fig.axes)]:
        if legend is not None:
            texts += legend.get_texts()
    for ax in fig.axes:
        texts += [ax.title, ax._left_title, ax._right_title, ax.xaxis.label, ax.yaxis.label]
        texts += list(ax.texts)
        for axis in (ax.xaxis, ax.yaxis):
            lo, hi = sorted(axis.get_view_interval())
            locs = axis.get_majorticklocs()
            for loc, tick in zip(locs, axis.get_major_ticks(len(locs)), strict=True):
                if lo <= loc <= hi:
                    texts += [label for label in (tick.label1, tick.label2)
                              if label.get_visible()]
    out = []
    for text in {id(t): t for t in texts}.values():
        if text.get_visible() and text.get_text().strip():
            box = (Annotation.get_window_extent(text, renderer) if isinstance(text, Annotation)
                   else text.get_window_extent(renderer))
            out.append((text.get_text(), box))
    return out


def overlapping_texts(fig):
    boxes = [(t, b.shrunk(0.98, 0.9)) for t, b in visible_texts(fig)]
    return [(a, b) for (a, ba), (b, bb) in itertools.combinations(boxes, 2) if ba.overlaps(bb)]


def pareto_summary(cpu, error=1.0, names=("fixed-10s", "esdf-innovation", "learned")):
    """Groups of two clutter levels, the points' CPU times from ``cpu`` (one per name)."""
    groups = []
    for level in (2, 3):
        for name, c in zip(names, cpu, strict=True):
            groups.append({"policy": name, "clutter_level": level, "total_cpu_s": c,
                           "interface_cpu_s": c, "map_error_m_succeeded": error,
                           "ci95": {"total_cpu_s": [0.9 * c, 1.1 * c],
                                    "map_error_m_succeeded": [0.8 * error, 1.2 * error]},
                           "n_values": {"total_cpu_s": 3, "interface_cpu_s": 3,
                                        "map_error_m_succeeded": 2}})
    return {"groups": groups}


@pytest.mark.parametrize("cpu", [
    (0.25, 0.3, 0.33),       # the pareto.png: 2x10^-1 ... 4x10^-1 ran together
    (0.012, 0.013, 0.045),   # pareto_interface.png's range
    (0.002, 0.2, 40.0),      # five decades
])
def test_pareto_ticks_labels_and_panels_never_overlap(cpu):
    from slam_gym.evaluation.plots import pareto_figure

    for x in ("total_cpu_s", "interface_cpu_s"):
        # two points at the same place: their numbers must not cover each other
        fig = pareto_figure(pareto_summary(cpu), x=x, title="Map error against compute")
        assert overlapping_texts(fig) == []
        for ax in fig.axes:
            labels = [t.get_text() for t in ax.xaxis.get_majorticklabels() if t.get_text()]
            assert 2 <= len(labels) <= 6 and all(len(t) <= 6 for t in labels), labels
            assert ax.get_xlabel() == ""  # one label for the panels, not one each
            assert sorted(t.get_text() for t in ax.texts) == ["2/3"] * 3
        assert "(s, log scale)" in fig.get_supxlabel()


def test_identical_traces_are_drawn_once_and_named_together():
    from slam_gym.evaluation.plots import nees_figure, uncertainty_figure

    a = np.linspace(1.0, 5.0, 50)
    series = {"fixed-10s": a, "esdf-innovation": a.copy(), "learned": a[::-1].copy()}
    note = "raiser: its run here is an error row"
    for fig, notes in ((nees_figure(series, dt_s=0.1, notes=[note]), [f"Not drawn: {note}"]),
                       (uncertainty_figure(series, dt_s=0.1), [])):
        ax = fig.axes[0]
        drawn = [line for line in ax.get_lines() if len(line.get_xdata()) == 50]
        assert len(drawn) == 2
        legend = [t.get_text() for t in ax.get_legend().get_texts()]
        assert any(t.startswith("fixed-10s = esdf-innovation (identical here)") for t in legend)
        assert not any(t.startswith("esdf-innovation") for t in legend)
        assert any(t.startswith("learned") for t in legend)
        assert [t.get_text() for t in fig.texts] == notes
        assert overlapping_texts(fig) == []


def test_the_map_title_says_when_and_where_a_drawn_run_failed():
    from slam_gym.evaluation.plots import run_map_figure

    path = np.column_stack([np.linspace(0, 50, 30), np.zeros(30), np.zeros(30)])
    kwargs = {"landmarks_true": [[10.0, 5.0]], "landmark_means": [[10.2, 5.1]],
              "landmark_covs": [np.eye(2) * 0.1], "path_true": path, "path_est": path,
              "title": "fixed-10s, clutter level 3, seed 0"}
    failed = run_map_figure(**kwargs, failure=(300.4, 41.0, 0.0))
    title = failed.axes[0].get_title()
    assert title.startswith("fixed-10s, clutter level 3, seed 0\nfailed at 300 s, at (41, 0) m")
    legend = [t.get_text() for t in failed.axes[0].get_legend().get_texts()]
    assert "where it failed (300 s)" in legend
    marker = [line for line in failed.axes[0].get_lines() if line.get_marker() == "X"]
    assert len(marker) == 1 and tuple(marker[0].get_xydata()[0]) == (41.0, 0.0)
    assert overlapping_texts(failed) == []
    ok = run_map_figure(**kwargs)
    assert ok.axes[0].get_title() == kwargs["title"]
    assert not any("failed" in t.get_text() for t in ok.axes[0].get_legend().get_texts())


def timeline(fused, optimised, flags, end_s=60.0, failed=False):
    t = np.arange(1.0, 61.0)
    mask = [np.isin(t, np.asarray(v, dtype=float)) for v in (fused, optimised, flags)]
    return {"t_s": t, "fused": mask[0], "optimised": mask[1], "closure_flag": mask[2],
            "end_s": end_s, "failed": failed, "n_fusions": len(fused),
            "n_optimisations": len(optimised), "true_loop_closure_s": None}


def test_the_decisions_legend_lists_only_what_is_drawn():
    from slam_gym.evaluation.timeline import decisions_figure

    fig = decisions_figure({"fixed-10s": timeline([10, 20], [], []),
                            "fixed-10s-optimise": timeline([10, 20], [10, 20], [])},
                           title="t", notes=["raiser: its run here is an error row"])
    legend = [t.get_text() for t in fig.legends[0].get_texts()]
    assert legend == ["fusion", "optimisation", "end of path"]
    assert [t.get_text() for t in fig.texts] == ["Not drawn: raiser: its run here is an error "
                                                 "row"]
    assert overlapping_texts(fig) == []
    fig = decisions_figure({"a": timeline([10], [], [30], end_s=40.0, failed=True)})
    legend = [t.get_text() for t in fig.legends[0].get_texts()]
    assert legend == ["fusion", "closure detected (CM Def. 1)", "failure (BB's criterion)"]
    triangles = [line for line in fig.axes[0].get_lines() if line.get_marker() == "v"]
    assert [list(line.get_xdata()) for line in triangles] == [[30.0]]


def test_the_success_figure_names_a_policy_with_no_ok_run():
    from slam_gym.evaluation.plots import success_figure

    groups = [{"policy": "fixed-10s", "scenario": "s", "clutter_level": 2, "n_ok": 3,
               "success_rate": 2 / 3, "success_ci95": [0.2, 0.94]},
              {"policy": "raiser", "scenario": "s", "clutter_level": 2, "n_ok": 0,
               "success_rate": None, "success_ci95": None}]
    fig = success_figure({"groups": groups})
    legend = [t.get_text() for t in fig.legends[0].get_texts()]
    assert legend == ["fixed-10s (3 runs per level)"]
    assert [t.get_text() for t in fig.texts] == [
        "Not drawn: raiser (no run finished without an error)"]
    assert overlapping_texts(fig) == []
