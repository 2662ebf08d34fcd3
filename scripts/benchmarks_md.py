"""Regenerate BENCHMARKS.md from the newest GPU benchmark JSONs under scripts/results/."""

from __future__ import annotations

import json
import sys
from datetime import datetime
from pathlib import Path

from bench_end_to_end import RAW_SAMPLE_BYTES  # the sample size of results that predate its record

ROOT = Path(__file__).resolve().parents[1]
RESULTS = ROOT / "scripts" / "results"
PEER_HOURS = 12
"""Newton runs this close in time to ours count as the same session's peer figures."""


def timed_text(runs: list[dict]) -> str:
    """How many frames each run timed (a pile's later frames, settled and touching, cost more than its first)."""
    counts = sorted({int(r["frames_timed"]) for r in runs if "frames_timed" in r})
    return " or ".join(map(str, counts)) + " timed frames from the start" if counts else "the timed frames"


def split_text(runs: list[dict]) -> str:
    """How the runs' phase split was measured (runs before the trajectory split have no rerun gap)."""
    if all("phase_rerun_gap_m" in r for r in runs):
        text = (
            "the timed frames run again from their start, each phase of a frame its own captured graph, timed"
            " on the device by events between them, so the parts add up to about the whole (on the GPU the rerun"
            " drifts from the timed run, as float atomics add in another order: `phase_rerun_gap_m` in the JSON)."
        )
        if any(r.get("collision_prepare_overlapped") for r in runs):
            text += (
                " A timed frame runs the collision stage's preparation beside the elastic launch; the split runs"
                " them one after the other, so where bodies collide its parts add up to a little more than the whole."
            )
        return text
    return (
        "each phase of a step captured as its own graph and replayed at the state the timed frames ended in"
        " (approximate: the parts need not add up to the whole)."
    )


def checked_run(runs: list[dict]) -> bool:
    """Whether the runs' dense checks read the timed run itself (newer JSON lists the frames checked) rather than
    a replay of its frames from their start."""
    return any("frames" in r.get("dense_check", {}) for r in runs)


def newest(pattern: str) -> tuple[Path, dict] | None:
    paths = sorted(RESULTS.glob(pattern))
    return (paths[-1], json.loads(paths[-1].read_text())) if paths else None


def scene_name(run: dict) -> str:
    """A run's row name: the scene, or the pile and its size."""
    if run["kind"] == "pile":
        return f"pile of {run['n']} armadillos"
    if run["kind"] == "mixed":
        return f"mixed pile of {run['n']}"
    return run["kind"]


def penetration_text(run: dict) -> str:
    """The run's dense penetration: the independent check's worst (bodies / ground, % of size) where present."""
    check = run.get("dense_check")
    if check is None:
        return f"{1e3 * run['dense_penetration_m']:.0f} mm"
    worst = check["worst"]
    return f"{100 * worst['relative']:.2f} % / {100 * worst['below_relative']:.2f} %"


def peer_runs(env: dict) -> tuple[dict[int, dict], list[Path], tuple[Path, dict] | None]:
    """Newton's figures for our run: every Newton JSON of the same device within PEER_HOURS of ours, the
    nearest in time first, so the nearest run of each pile size wins (a Newton crash on a large pile ends its
    process: the sizes after it come from a separate run). Returns the runs by pile size, the files they come
    from, and the nearest file with its data (None if none is in the window)."""
    ours_at = datetime.fromisoformat(env["date"])
    peers = []
    for candidate in RESULTS.glob("bench-newton-cuda*.json"):
        peer_data = json.loads(candidate.read_text())
        gap = abs((datetime.fromisoformat(peer_data["environment"]["date"]) - ours_at).total_seconds())
        if peer_data["environment"]["device"] == env["device"] and gap <= PEER_HOURS * 3600:
            peers.append((gap, candidate, peer_data))
    peers = [(candidate, peer_data) for _, candidate, peer_data in sorted(peers, key=lambda item: item[0])]
    newton: dict[int, dict] = {}
    used = []  # the peer files a figure is taken from
    for candidate, peer_data in peers:
        fresh = [r for r in peer_data["runs"] if r["n"] not in newton]
        newton.update((r["n"], r) for r in fresh)
        if fresh:
            used.append(candidate)
    return newton, used, peers[0] if peers else None


def settings_text(data: dict) -> str:
    """The scene settings a run was given on the command line (``bench.py --set``), as a clause; none: empty."""
    settings = data.get("settings") or []
    return f", with `--set {' '.join(settings)}`" if settings else ""


def header_lines(path: Path, data: dict, used: list[Path], peer: tuple[Path, dict] | None) -> list[str]:
    """The title, where the figures come from (ours and the peer's) and how they are taken."""
    env = data["environment"]
    lines = [
        "# Benchmarks",
        "",
        "Generated by `scripts/benchmarks_md.py` from the newest JSON under `scripts/results/`; produced by",
        "`scripts/bench.py` (ours) and `scripts/bench_newton.py` (the peer) on the GPU machine. Do not edit by hand.",
        "",
        f"- ours: `{path.name}` — {env['device']}, driver {env['driver']}, Warp {env['warp']}, "
        f"commit `{env['commit'][:10]}`{settings_text(data)}",
    ]
    if peer:
        penv = peer[1]["environment"]
        names = ", ".join(f"`{p.name}`" for p in used)
        lines.append(
            f"- peer: {names} — Newton {penv.get('newton', '')} `SolverVBD`, {penv['device']}, within "
            f"{PEER_HOURS} hours (the nearest run of each size) and the same tet meshes, 10 substeps x 10 "
            "iterations per frame, self-contact on; pile sizes missing here have no Newton run in that window "
            "(Newton 1.8 has crashed with an illegal memory access on 256 and more on the H100, on 64 on the H200;"
            " logs beside the JSON)"
        )
    return lines + [
        "",
        "Per 1/60 s frame: stepping, collisions and dense mapping on the device (a replayed CUDA graph), file",
        f"output excluded; 2 warm-up frames, then {timed_text(data['runs'])}. Phase split: " + split_text(data["runs"]),
        "Output, the USD file writing, is outside the frame time. Dense penetration: measured on the dense meshes",
        "alone (warpfem.io.penetration), the worst over "
        + ("the frames of the run its JSON lists," if checked_run(data["runs"]) else "a replay of the timed frames,")
        + " a vertex inside another",
        "body's dense surface / below the ground, relative to the body's size (runs before that check: the",
        "collider's own estimate at the end, in mm); lowest point: ours the lowest dense vertex at the end,",
        "Newton's its lowest tet vertex (ground at 0); Newton's dense penetration: the same dense meshes carried",
        "by its tets with our embedding's weights, checked the same way on the same frames (blank: a peer run",
        'before that check). Substeps: the scene\'s; "4 (x2 in 12 of 120)": 12 of the',
        "timed frames ran twice that many (`[collision] approach_limit`: bodies closing fast on each other);",
        '"4 (more in 12 of 120, 1.07x the steps)": 12 ran 1.5 or 2 times that many, the steps 1.07 times the',
        "scene's; the phase split runs every frame at the scene's substeps, so there its parts add up to less",
        "than the whole.",
    ]


def substeps_text(run: dict) -> str:
    """The run's substeps, and in how many timed frames more (bodies closing fast on each other)."""
    refined, frames = run.get("refined_frames", 0), run["frames_timed"]
    if not refined:
        return str(run["substeps"])
    if "steps_timed" not in run:  # runs from before a refined frame could run 1.5 times the substeps
        return f"{run['substeps']} (x2 in {refined} of {frames})"
    share = run["steps_timed"] / (run["substeps"] * frames)
    return f"{run['substeps']} (more in {refined} of {frames}, {share:.2f}x the steps)"


def main_table_lines(data: dict, newton: dict[int, dict]) -> list[str]:
    """Every GPU run: sizes, frame time and its phases, CG, contacts, penetration, and Newton beside the piles."""
    lines = [
        "",
        "| scene | substeps | bodies | tets | dense triangles | ms/frame | fps | elastic | collision | solve | map"
        " | output | CG it/step | contacts max/step | dense penetration | lowest point | Newton ms/frame"
        " | Newton dense penetration | Newton lowest | speed-up |",
        "| --- | --- | --- | --- | --- | --- | --- | --- | --- | --- | --- | --- | --- | --- | --- | --- | --- | --- "
        "| --- | --- |",
    ]
    own_tolerance: dict[str, float] = {}  # each scene's first run has the scene file's own CG settings
    for r in data["runs"]:
        p = r["phase_ms"]
        name = scene_name(r)
        tolerance = own_tolerance.setdefault(r["kind"], r.get("cg_tolerance"))
        if r.get("cg_tolerance") != tolerance:
            name += f", CG to {r['cg_tolerance']:g}"
        peer_run = newton.get(r["n"]) if r["kind"] == "pile" else None
        peer_cols = (
            f"{peer_run['ms_per_frame']:.1f} | {penetration_text(peer_run) if peer_run.get('dense_check') else ''} | "
            f"{1e3 * peer_run['lowest_point_m']:+.1f} mm | {peer_run['ms_per_frame'] / r['ms_per_frame']:.1f}x"
            if peer_run
            else "| | |"
        )
        output = f"{p['output']:.1f}" if "output" in p else ""
        lines.append(
            f"| {name} | {substeps_text(r)} | {r['bodies']} | {r['tets']:,} | {r['dense_triangles']:,} | "
            f"{r['ms_per_frame']:.2f} | {r['fps']:.0f} | {p.get('elastic', 0):.2f} | {p.get('collision', 0):.2f} | "
            f"{p.get('solve', 0):.2f} | {p.get('map', 0):.2f} | {output} | {r['cg_iterations_per_step']:.0f} | "
            f"{r['contacts_max_per_step']:,} | {penetration_text(r)} | "
            f"{1e3 * r['lowest_dense_point_m']:+.0f} mm | {peer_cols} |"
        )
    return lines


def large_pile_lines(found: tuple[Path, dict] | None) -> list[str]:
    """The pile of 1,024, run on its own (``scripts/bench.py --piles 1024``), with its dense penetration at the
    last frame, and over the run where it was checked there (``--check-bodies 1024``)."""
    if not found:
        return []
    path, data = found
    env = data["environment"]
    over = all(r["dense_check"].get("frames_checked", 1) > 1 for r in data["runs"])
    lines = [
        "",
        "## The pile of 1,024",
        "",
        f"`{path.name}` (commit `{env['commit'][:10]}`{settings_text(data)}, {env['device']}): 64 layers of 16,"
        " the upper ones still falling at the end of the timed frames; dense penetration "
        + ("worst over the frames checked / at that end" if over else "at that end only")
        + " (inside another body / below the ground, relative to the body's size).",
        "",
        "| scene | substeps | tets | dense triangles | ms/frame | CG it/step | "
        + ("worst / at the end |" if over else "at the end |"),
        "| --- | --- | --- | --- | --- | --- | --- |",
    ]
    for r in data["runs"]:
        end, worst = r["dense_check"]["end"], r["dense_check"]["worst"]
        depth = f"{100 * end['relative']:.2f} % / {100 * end['below_relative']:.2f} %"
        if over:
            depth = f"{100 * worst['relative']:.2f} / {depth}"
        lines.append(
            f"| {scene_name(r)} | {substeps_text(r)} | {r['tets']:,} | {r['dense_triangles']:,} | "
            f"{r['ms_per_frame']:.1f} | {r['cg_iterations_per_step']:.0f} | {depth} |"
        )
    return lines


def before_after_lines(data: dict, newton: dict[int, dict]) -> list[str]:
    """The same scenes at an earlier commit on the same device (the newest ``before-*.json``): speed and the
    dense check side by side, before and after; the header says how far apart the runs were where not within
    PEER_HOURS."""
    env = data["environment"]
    ours_at = datetime.fromisoformat(env["date"])
    found = None
    for candidate in sorted(RESULTS.glob("before-*.json")):
        before = json.loads(candidate.read_text())
        benv = before["environment"]
        gap = abs((datetime.fromisoformat(benv["date"]) - ours_at).total_seconds())
        if benv["device"] == env["device"] and benv.get("driver") == env.get("driver"):
            found = (candidate, before, gap)
    if found is None:
        return []
    path, before, gap = found
    if gap <= 3600:
        when = f"{gap / 60:.0f} minutes apart"
    else:
        when = f"{gap / 3600:.1f} hours apart, in another lease of it"
    old = {(r["kind"], r["n"]): r for r in before["runs"]}
    for part in before["environment"].get("parts", []):  # a part run far from the others: say which, and when
        part_gap = (ours_at - datetime.fromisoformat(part["date"])).total_seconds()
        if abs(part_gap) > 3600 and abs(abs(part_gap) - gap) > 3600:  # not with the rest
            side = "earlier" if part_gap > 0 else "later"
            when += f" (its `{part['command']}` {abs(part_gap) / 3600:.1f} hours {side}, in another lease of it)"
    lines = [
        "",
        "## Before and after",
        "",
        f"`{path.name}`: commit `{before['environment']['commit'][:10]}` on the same device and driver, {when},"
        " each commit with its own scene defaults and its own preprocessing; dense penetration worst over the"
        " timed frames / at their end, inside another body and below the ground, relative to the body's size, as"
        " above.",
        "",
        "| scene | ms/frame before | after | after / before | inside another body, before | after"
        " | below the ground, before | after | Newton ms/frame | speed-up after |",
        "| --- | --- | --- | --- | --- | --- | --- | --- | --- | --- |",
    ]
    for r in data["runs"]:
        b = old.get((r["kind"], r["n"]))
        if b is None or "dense_check" not in b or "dense_check" not in r:
            continue
        peer_run = newton.get(r["n"]) if r["kind"] == "pile" else None
        peer = (
            f"{peer_run['ms_per_frame']:.1f} | {peer_run['ms_per_frame'] / r['ms_per_frame']:.1f}x"
            if peer_run
            else " |"
        )
        cells = []
        for key in ("relative", "below_relative"):
            for run in (b, r):
                check = run["dense_check"]
                cells.append(f"{100 * check['worst'][key]:.2f} / {100 * check['end'][key]:.2f} %")
        lines.append(
            f"| {scene_name(r)} | {b['ms_per_frame']:.2f} | {r['ms_per_frame']:.2f} | "
            f"{r['ms_per_frame'] / b['ms_per_frame']:.2f}x | {' | '.join(cells)} | {peer} |"
        )
    return lines


def tolerance_lines(data: dict) -> list[str]:
    """The paper scenes' CG tolerances against the error CG alone adds in one frame."""
    trade = [r for r in data["runs"] if "frame_error" in r and r["kind"] != "pile"]
    if not trade:
        return []
    lines = [
        "",
        "## CG tolerance against accuracy (the paper's scenes)",
        "",
        "One frame error: from the state the timed frames ended in, one frame with the run's CG settings against",
        "the same frame with CG converged to 1e-6 (same state, same substeps), the largest and rms distance of",
        "the tet vertices. It is the error CG alone adds in a frame; a whole run's end would mostly measure how",
        "chaotic a stack is. The project's `default` quality preset stops CG at 1e-3, the paper scenes at 1e-4.",
        "",
        "| scene | substeps | CG tolerance | ms/frame | fps | CG it/step | one-frame error max / rms"
        " | deepest contact | dense penetration |",
        "| --- | --- | --- | --- | --- | --- | --- | --- | --- |",
    ]
    for r in trade:
        e = r["frame_error"]
        lines.append(
            f"| {r['kind']} | {r['substeps']} | {r['cg_tolerance']:g} | {r['ms_per_frame']:.2f} | {r['fps']:.0f} | "
            f"{r['cg_iterations_per_step']:.0f} | {1e3 * e['max_m']:.2f} / {1e3 * e['rms_m']:.3f} mm | "
            f"{1e3 * r['contact_depth_max_m']:.1f} mm | {1e3 * r['dense_penetration_m']:.0f} mm |"
        )
    return lines


def deviation_lines(data: dict, newton: dict[int, dict]) -> list[str]:
    """Settled piles against a converged run of each, ours and Newton's."""
    deviations = [
        (r["n"], r["settle_deviation"], newton.get(r["n"], {}).get("settle_deviation"))
        for r in data["runs"]
        if r["kind"] == "pile" and "settle_deviation" in r
    ]
    if not deviations:
        return []
    lines = [
        "",
        "## Settled pile against a converged run",
        "",
        "Tet vertex positions after the timed scene's frame count, bench settings against a converged run of the",
        "same pile (ours: 4x substeps, CG to 1e-6; Newton: 4x substeps, 4x iterations). A dropped armadillo",
        "bounces and topples, so this measures how chaotic the drop is as much as the solver's accuracy.",
        "",
        "| pile | ours max / rms | Newton max / rms |",
        "| --- | --- | --- |",
    ]
    for n, ours_dev, peer_dev in deviations:
        theirs = f"{peer_dev['max_m']:.3f} / {peer_dev['rms_m']:.3f} m" if peer_dev else "not measured"
        lines.append(f"| {n} | {ours_dev['max_m']:.3f} / {ours_dev['rms_m']:.3f} m | {theirs} |")
    return lines


def cg_scale_lines(data: dict) -> list[str]:
    """One CG iteration on a box of about a million tets against its memory-traffic floor."""
    cg = data.get("cg_at_scale")
    if not cg:
        return []
    lines = [
        "",
        "## One CG iteration at scale",
        "",
        f"A {cg['tets']:,}-tet box ({cg['nnz_blocks']:,} 3x3 blocks): "
        f"**{cg['cg_iteration_us']:.0f} µs per block-Jacobi PCG iteration**,",
        f"against {cg['spmv_floor_us']:.0f} µs that one SpMV's memory traffic ({cg['spmv_bytes'] / 1e6:.0f} MB) "
        f"needs at the {cg['stream_bandwidth_GBps']:.0f} GB/s",
        f"a streaming copy reached in the same run: **{cg['ratio_to_spmv_floor']:.1f}x** the floor "
        "(an iteration also streams the update vectors).",
    ]
    if "stored_blocks" in cg:
        by_chunk = ", ".join(f"{k}: {v:.0f} µs" for k, v in cg["cg_iteration_us_by_chunk"].items())
        lines += [
            f"We store the upper triangle ({cg['stored_blocks']:,} blocks; its own product floor "
            f"{cg['stored_spmv_floor_us']:.0f} µs). Iteration time by blocks per thread of the product: "
            f"{by_chunk} (64: in effect a thread per row).",
        ]
    return lines


def cpu_lines(found: tuple[Path, dict] | None) -> list[str]:
    """The newest CPU run of the bench: frame time, CG and penetration per scene."""
    if not found:
        return []
    cpu_env = found[1]["environment"]
    lines = [
        "",
        "## On the CPU",
        "",
        f"`{found[0].name}` (commit `{cpu_env['commit'][:10]}`, Python {cpu_env['python']}, Warp {cpu_env['warp']}; "
        "the CI machine's kind, 2 cores; Warp runs CPU kernels on one thread). Dense penetration as above "
        "(runs before that check: the collider's own estimate at the end, in mm):",
        "",
        "| scene | substeps | ms/frame | fps | CG it/step | dense penetration |",
        "| --- | --- | --- | --- | --- | --- |",
    ]
    for r in found[1]["runs"]:
        lines.append(
            f"| {scene_name(r)} | {r['substeps']} | {r['ms_per_frame']:.1f} | {r['fps']:.0f} | "
            f"{r['cg_iterations_per_step']:.0f} | {penetration_text(r)} |"
        )
    return lines


def main() -> int:
    ours = newest("bench-full-cuda*.json")
    if ours is None:
        print("no bench-full-cuda*.json under scripts/results", file=sys.stderr)
        return 1
    path, data = ours
    newton, used, peer = peer_runs(data["environment"])
    lines = header_lines(path, data, used, peer)
    lines += main_table_lines(data, newton)
    lines += large_pile_lines(newest("pile1024-cuda*.json"))
    lines += before_after_lines(data, newton)
    lines += tolerance_lines(data)
    lines += deviation_lines(data, newton)
    lines += cg_scale_lines(data)
    lines += cpu_lines(newest("bench-full-cpu*.json"))
    lines += end_to_end_lines(newest("bench-end-to-end-cuda*.json"))
    lines += end_to_end_lines(newest("bench-end-to-end-cpu*.json"), "on the CPU")
    (ROOT / "BENCHMARKS.md").write_text("\n".join(lines) + "\n")
    print("wrote BENCHMARKS.md")
    return 0


def end_to_end_lines(found: tuple[Path, dict] | None, where: str = "") -> list[str]:
    """The end-to-end table (``scripts/bench_end_to_end.py``): what a user waits for, the file written.

    ``where``: added to the heading (a second table, e.g. the CPU's).
    """
    if not found:
        return []
    path, data = found
    env = data["environment"]
    machine = f"driver {env['driver']}" if env.get("driver") else f"Python {env.get('python', '?')}"
    sampled = ""
    if any("raw_sampled_frames" in r for r in data["runs"]):
        mb = f"{data.get('raw_sample_bytes', RAW_SAMPLE_BYTES) / 2**20:g} MB"
        sampled = (
            f", per frame of the frames it was written beside: every frame up to {mb} of points, one in"
            f" ceil(size / {mb}) above, so that measuring it does not hold the writer up"
        )
    lines = [
        "",
        f"## End to end: the file written{', ' + where if where else ''}",
        "",
        f"`{path.name}` ({env['device']}, {machine}, Warp {env['warp']}, commit `{env['commit'][:10]}`): "
        f"`warpfem run` of {data['frames']} frames to a real file, each case in a fresh process. Per frame: "
        "wall from the first step to the file written; simulate (the stepping thread, including its waits for "
        "the interpreter lock); write and check, each on a thread of its own beside it; close, the ms of the "
        "run from the last frame's hand-over to the file written (part of wall, where the JSON has it); raw, "
        "writing the same bytes with one plain write a frame to the same disk on the writer's thread in the "
        f"same run{sampled} (in "
        "parentheses: written again alone after the run, where the JSON has it), and write / raw against each; "
        "peak resident memory of the whole process; the file with its clips.",
        "",
        *(
            ["The writer cases (`writerN`) feed N points a frame to the writer alone, as fast as it takes them.", ""]
            if any(r["case"].startswith("writer") for r in data["runs"])
            else []
        ),
        "| case | bodies | dense vertices | writer processes | wall ms | simulate | write | check | close ms "
        "| raw write | wall / max(simulate, write) | write / raw | peak memory (caller + each process) | file |",
        "| --- | --- | --- | --- | --- | --- | --- | --- | --- | --- | --- | --- | --- | --- |",
    ]
    for r in data["runs"]:
        if "error" in r:
            lines.append(f"| {r['case']} | failed: {' '.join(r['error'])} |" + " |" * 12)
            continue
        lines.append(end_to_end_row(r))
    return lines


def end_to_end_row(r: dict) -> str:
    """One case of the end-to-end table; a writer-only case has no simulation, check or bodies."""
    ms = r["ms_per_frame"]
    if "bodies" in r:
        wall, simulate, write, check = (f"{ms[k]:.2f}" for k in ("wall", "simulate", "write", "check"))
        bodies, ratio = str(r["bodies"]), f"{r['wall_over_larger_of_simulate_and_write']:.2f}"
    else:
        wall = write = f"{ms['wall']:.2f}"
        simulate = check = bodies = ratio = "-"
    peak = f"{r['peak_rss_mb'] / 1024:.2f} + {r.get('writer_peak_rss_mb', 0) / 1024:.2f} GB"
    file = f"{r['file_bytes'] / 2**20:,.0f} MB{' (clips)' if r['clips'] else ''}"
    close = f"{r['close_ms']:.1f}" if "close_ms" in r else "-"
    cells = [r["case"], bodies, f"{r['dense_vertices']:,}", str(r.get("writers", 0)), wall, simulate, write, check]
    cells.append(close)
    raw, over = f"{r['raw_write_ms_per_frame']:.2f}", f"{r['write_over_raw']:.1f}"
    if "raw_alone_ms_per_frame" in r and "bodies" in r:
        alone = r["raw_alone_ms_per_frame"]
        raw, over = f"{raw} ({alone:.2f})", f"{over} ({ms['write'] / max(alone, 1e-9):.1f})"
    cells += [raw, ratio, over, peak, file]
    return "| " + " | ".join(cells) + " |"


if __name__ == "__main__":
    sys.exit(main())
