"""Issue 18's speed targets against the benchmarks' latest results: one row each, met or not.

Reads the JSON files that the benchmark scripts wrote to `benchmarks/results/` and runs
nothing itself, so rerun the benchmarks first. Each row gives its figure from every run
passed (several `bench_core.py` runs with `--core`, and so on) and says in how many of
them the target was met. It prints a Markdown table and writes `results/targets.json`.

    PYTHONPATH=src python benchmarks/targets.py \\
        --core core_run1.json core_run2.json core.json --batch batch.json

Files are looked up in `benchmarks/results/` unless a path to an existing file is given.
Where the figures come from:

| rows | file | command |
|---|---|---|
| L2, FC, DCT, PS + FC, time per pixel, 16 MP memory | `core.json` | `bench_core.py` |
| batch of 8, 64 captures' memory | `batch.json` | `bench_batch.py` |
| command line | `cli.json` | `bench_cli.py` |
| MLP relighting | `brdf.json` (`--brdf`: one or more runs) | `bench_brdf.py --part speed` |
| bilateral integration | `integration.json` | `bench_integration.py` |
| robust L1 (`irls`) | `robust.json` | `bench_robust.py` |
"""

from __future__ import annotations

import json
import pathlib
import sys

try:
    from benchmarks._common import RESULTS, arguments, write_json
except ImportError:  # run as a script
    sys.path.insert(0, str(pathlib.Path(__file__).resolve().parents[1]))
    from benchmarks._common import RESULTS, arguments, write_json

BATCH_ROWS = {  # issue 18: "throughput at least 1.0x that of 8 single calls"
    "numpy stacks": "batch_over_single_throughput",
    "aligned host stacks": "batch_over_single_throughput_aligned",
    "stacks on the device": "batch_over_single_throughput_on_device",
    "aligned, `out=` stream": "reusing_out_over_single_throughput_aligned",
    "aligned, every batch into fresh outputs": "fresh_over_single_throughput_aligned",
    "dropping samples": "batch_over_single_throughput_aligned_dropped",
    "dropping samples, `out=`": "reusing_out_over_single_throughput_aligned_dropped",
    "dropping samples, every batch into fresh outputs":
        "fresh_over_single_throughput_aligned_dropped",
    "K=12": "batch_over_single_throughput_aligned_k12",
}


def load(name: str) -> dict:
    path = pathlib.Path(name)
    return json.loads((path if path.is_file() else RESULTS / name).read_text())


def core_ratio(run: dict, work: str, k: int | None = None) -> float:
    """The `ratio` (jaxps over its baseline, same run) of a `bench_core.py` row."""
    (row,) = [r for r in run["rows"] if r["work"] == work and r["impl"].startswith("jaxps")
              and (k is None or r.get("K") == k)]
    return row["ratio"]


def bare_note(core: list[dict], work: str, k: int) -> str:
    """The bare XLA kernel's ratio to numpy and jaxps's to the bare kernel (`bench_core.py`'s
    `bare_l2`), in the runs that measured it, as a note."""
    pairs = []
    for run in core:
        bare = [r for r in run["rows"] if r["work"] == work and r.get("K") == k
                and r["impl"].startswith("bare")]
        ours = [r for r in run["rows"] if r["work"] == work and r.get("K") == k
                and r["impl"].startswith("jaxps") and "over_bare_kernel" in r]
        if bare and ours:
            pairs.append((bare[0]["ratio"], ours[0]["over_bare_kernel"]))
    if not pairs:
        return ""
    return ("bare XLA kernel of normals and albedo over numpy, same runs: "
            + ", ".join(f"{b:.2f}x" for b, _ in pairs) + "; jaxps over it: "
            + ", ".join(f"{o:.2f}x" for _, o in pairs))


def spread(run: dict, key: str) -> float:
    """Largest over smallest time per pixel across `bench_core.py`'s image sizes."""
    values = [s[key] for s in run["scaling"]]
    return max(values) / min(values)


def baseline_spread(core: list[dict], key: str, label: str) -> str:
    """`spread` of a baseline's time per pixel in the runs that measured it, as a note."""
    values = [spread(r, key) for r in core if key in r["scaling"][0]]
    return f"{label}: " + ", ".join(f"{v:.2f}x" for v in values) if values else ""


def target(name, values, bound, at_most=True, unit="x", source="", note=""):
    """One row: `values` (one per run) held to `bound`."""
    met = [v <= bound if at_most else v >= bound for v in values]
    return {"target": name, "bound": f"{'<=' if at_most else '>='} {bound:g}{unit}",
            "values": [round(v, 3) for v in values], "unit": unit,
            "met_runs": sum(met), "runs": len(values), "source": source, "note": note}


def rows(core: list[dict], batch: list[dict], cli: list[dict], brdf: list[dict] | None,
         integration: dict | None, robust: dict | None) -> list[dict]:
    out = []
    if core:
        src = "bench_core.py"
        out += [
            target("L2 PS, K=5, 1 MP, over numpy pinv-matmul + normalise",
                   [core_ratio(r, "ps_l2", 5) for r in core], 0.6, source=src,
                   note=bare_note(core, "ps_l2", 5)),
            target("L2 PS, K=12, over numpy", [core_ratio(r, "ps_l2", 12) for r in core], 1.0,
                   source=src, note=bare_note(core, "ps_l2", 12)),
            target("L2 PS, K=12, ~5% of samples dropped, over numpy",
                   [core_ratio(r, "ps_l2_dropped", 12) for r in core], 1.5, source=src,
                   note=bare_note(core, "ps_l2_dropped", 12)),
            target("Frankot-Chellappa from the normals, over scipy.fft on the gradients",
                   [core_ratio(r, "fc") for r in core], 1.0, source=src),
            target("DCT Poisson from the normals, over scipy.fft's from the gradients",
                   [core_ratio(r, "dct") for r in core], 1.0, source=src,
                   note="jaxps also computes the height steps from the normals"),
            target("DCT Poisson solve from the same gradients as scipy's",
                   [core_ratio(r, "dct_solve") for r in core], 1.0, source=src),
            target("L2 PS + FC, over numpy PS + scipy FC",
                   [core_ratio(r, "ps_l2+fc", 5) for r in core], 1.0, source=src),
            target("time per pixel 0.26-16 MP, L2 PS: largest over smallest",
                   [spread(r, "ps_l2_ns_per_px") for r in core], 1.3, source=src,
                   note="; ".join(filter(None, [
                       baseline_spread(core, "numpy_ps_ns_per_px", "numpy's PS, same runs"),
                       baseline_spread(core, "bare_ps_ns_per_px", "the bare XLA kernel")]))),
            target("time per pixel 0.26-16 MP, FC: largest over smallest",
                   [spread(r, "fc_ns_per_px") for r in core], 1.3, source=src,
                   note=baseline_spread(core, "scipy_fc_ns_per_px", "scipy's FC, same runs")),
            target("16 MP five-frame capture, peak RSS",
                   [r["peak_memory"]["peak_rss_gb"] for r in core], 6.0, unit=" GB",
                   source=src),
        ]
    for label, key in BATCH_ROWS.items() if batch else ():
        out.append(target(f"batch of 8 x 1 MP over 8 single calls, {label}",
                          [b[key] for b in batch], 1.0, at_most=False, source="bench_batch.py"))
    if batch:
        out.append(target("64 captures of 1 MP, peak RSS (clean, chunks of 8; dropping "
                          "samples, default chunks)",
                          [m for b in batch for m in (
                              b["batch_peak_memory"]["peak_rss_gb"],
                              *(d["peak_rss_gb"] for d in b.get("batch_peak_memory_dropped", [])
                                if d["chunk"] is None))],
                          8.0, unit=" GB", source="bench_batch.py"))
    if cli:
        rec = [c["reconstruct"] for c in cli]
        out += [
            target("`jaxps --help`", [c["start_up_s"]["jaxps --help"] for c in cli], 0.5,
                   unit=" s", source="bench_cli.py"),
            target("`jaxps reconstruct`, five 1 MP 16-bit PNGs, first run (empty cache)",
                   [r["1280x1024"]["first (empty cache)"]["wall_s"] for r in rec], 6.0,
                   unit=" s", source="bench_cli.py"),
            target("the same, second run", [r["1280x1024"]["second (warm cache)"]["wall_s"]
                                            for r in rec], 2.0, unit=" s",
                   source="bench_cli.py"),
            target("`jaxps reconstruct`, five 192x168 frames, second run",
                   [r["192x168"]["second (warm cache)"]["wall_s"] for r in rec], 1.5,
                   unit=" s", source="bench_cli.py"),
        ]
    if brdf:  # each run's `mlp` and `mlp_ratio`, in turn
        out.append(target("MLP relighting of 700x850 (median; `mlp`, `mlp_ratio` of each run)",
                          [r["speed"]["relight"][f"relight_{m}"]["ms_median"]
                           for r in brdf for m in ("mlp", "mlp_ratio")], 5.0, unit=" ms",
                          source="bench_brdf.py --part speed"))
    if integration:
        objects = integration["objects"]
        out.append(target("bilateral integration per DiLiGenT object, with intrinsics ("
                          + ", ".join(objects) + ")",
                          [objects[o]["bilateral persp"]["run_s"] for o in objects], 0.3,
                          unit=" s", source="bench_integration.py"))
    if robust:
        irls = robust["ours"]["irls"]
        same = robust["baseline"]["L1"]
        out.append(target("robust `irls` (L1), 1 MP, K=5", [irls["run_s"]], 0.15, unit=" s",
                          source="bench_robust.py",
                          note=f"median error {same['ours_on_same_pixels']['irls']['median_deg']:.2f}"
                               f" deg against RobustPhotometricStereo's L1 "
                               f"{same['error_subset']['median_deg']:.2f} on the same pixels"))
    return out


def machine(result: dict) -> str:
    """The CPU a result was measured on (`_common.environment`), or "not recorded"."""
    env = result.get("env") or result.get("machine") or result.get("setup") or {}
    return env.get("cpu") or "not recorded"


def markdown(table: list[dict]) -> str:
    lines = ["| target | bound | figure (each run) | met |", "|---|---|---|---|"]
    for r in table:
        figures = ", ".join(f"{v:.3f}" for v in r["values"]) + r["unit"]
        note = f" ({r['note']})" if r["note"] else ""
        met = ("yes" if r["met_runs"] == r["runs"] else
               "no" if r["met_runs"] == 0 else f"{r['met_runs']} of {r['runs']}")
        lines.append(f"| {r['target']}{note} | {r['bound']} | {figures} | {met} |")
    return "\n".join(lines)


def main(argv=None) -> dict:
    def options(p):
        p.add_argument("--core", nargs="+", default=["core.json"], metavar="JSON")
        p.add_argument("--batch", nargs="+", default=["batch.json"], metavar="JSON")
        p.add_argument("--cli", nargs="+", default=["cli.json"], metavar="JSON")
        p.add_argument("--brdf", nargs="+", default=["brdf.json"], metavar="JSON",
                       help="runs of bench_brdf.py --part speed (those that exist are read)")
        p.add_argument("--integration", default="integration.json", metavar="JSON",
                       help="a run of bench_integration.py (read if it exists)")
        p.add_argument("--robust", default="robust.json", metavar="JSON",
                       help="a run of bench_robust.py (read if it exists)")
        p.add_argument("--out", default="targets", help="results/OUT.json")

    args = arguments(__doc__, configure=options, argv=argv)
    def exists(name):
        return pathlib.Path(name).is_file() or (RESULTS / name).is_file()

    optional = {kind: load(name) if exists(name) else None
                for kind, name in (("integration", args.integration), ("robust", args.robust))}
    brdf = [b for b in args.brdf if exists(b)]
    optional["brdf"] = [load(b) for b in brdf]
    names = {"core": args.core, "batch": args.batch, "cli": args.cli, "brdf": brdf}
    inputs = {kind: [load(n) for n in names[kind]] for kind in ("core", "batch", "cli")}
    table = rows(inputs["core"], inputs["batch"], inputs["cli"], **optional)
    # the same-run ratios depend on the CPU, and the machines change from day to day
    inputs["brdf"] = optional["brdf"]
    for kind in ("integration", "robust"):
        if optional[kind] is not None:
            names[kind], inputs[kind] = [getattr(args, kind)], [optional[kind]]
    machines = {f"{kind} {name}": machine(result) for kind in names
                for name, result in zip(names[kind], inputs[kind], strict=True)}
    payload = {"command": "PYTHONPATH=src python benchmarks/targets.py "
                          + " ".join(sys.argv[1:] if argv is None else argv),
               "inputs": {"core": args.core, "batch": args.batch, "cli": args.cli, "brdf": brdf,
                          **{k: getattr(args, k) for k, v in optional.items()
                             if k != "brdf" and v is not None}},
               "machines": machines, "targets": table}
    path = write_json(args.out, payload)
    print(markdown(table))
    for cpu in sorted(set(machines.values())):
        print(f"on {cpu}: " + ", ".join(k for k, v in machines.items() if v == cpu))
    print(f"wrote {path}")
    return payload


if __name__ == "__main__":
    main()
