"""``make bench`` (``python -m bench``): latency, CPU and memory of the arena against its floors and MAVProxy.

The command line only: what each part measures is said in :mod:`bench.run`.
"""

from __future__ import annotations

from pathlib import Path
from typing import Annotated, Any

import typer

# -- the options, declared once each -------------------------------------------------------------------------

Part = Annotated[
    list[str] | None,
    typer.Option("--part", "-p", help="pipeline, floor, peer or micro (repeatable; default: all)."),
]
Vehicles = Annotated[str | None, typer.Option("--vehicles", "-n", help="Vehicle counts (default 1,20).")]
Rates = Annotated[str | None, typer.Option("--rates", "-r", help="Mocap rates in Hz (default 180).")]
Floor = Annotated[
    list[str] | None,
    typer.Option("--floor", help="Floor transports: zenoh, udp (repeatable; default both)."),
]
Duration = Annotated[float | None, typer.Option("--duration", "-d", help="Seconds measured per load point.")]
Warmup = Annotated[float | None, typer.Option("--warmup", help="Seconds of flow before measuring.")]
Quick = Annotated[
    bool,
    typer.Option("--quick", help="Short runs of 1 and 10 vehicles at 180 Hz (a check, not figures)."),
]
Profile = Annotated[
    bool, typer.Option("--profile", help="py-spy the services during each pipeline measurement.")
]
RealisticVision = Annotated[
    float,
    typer.Option(
        "--realistic-vision",
        help="Vision rate (Hz) of one more point per vehicle count, as deployed (0: skip).",
    ),
]
Overload = Annotated[
    int | None,
    typer.Option(
        "--overload",
        help="CPU hogs beside the deployed point at the largest load, measured again (default 2; 0: skip).",
    ),
]
PeerRepeats = Annotated[
    int | None,
    typer.Option("--peer-repeats", help="Runs of each forwarder in the peer comparison (default 3)."),
]
PeerDuration = Annotated[
    float | None, typer.Option("--peer-duration", help="Seconds per run of each forwarder (default 2.5).")
]
Hops = Annotated[
    bool,
    typer.Option("--hops", help="Also time each stage of the first vehicle (subscribes to its keys)."),
]
Decimate = Annotated[
    list[str] | None,
    typer.Option(
        "--decimate",
        help="Pipeline configurations: downsampler (chain arena), transform (arena-td); default both.",
    ),
]
VehicleMode = Annotated[
    str,
    typer.Option(
        "--vehicle-mode",
        help="zenoh.vehicle_mode of the pipeline's config: client, same (default: the config's default).",
    ),
]
Fleet = Annotated[
    int | None,
    typer.Option(
        "--fleet",
        help="Vehicles of the fleet point (deployed vision, every configuration; default 50 unless "
        "--vehicles is given, 0: skip).",
    ),
]
Growth = Annotated[
    str | None,
    typer.Option(
        "--growth",
        help="Vehicle counts of the 'How cost grows' table, each deployed as the fleet is (default "
        "1,10,20,50 unless --vehicles is given; 0: skip).",
    ),
]
GatewayHosts = Annotated[
    int,
    typer.Option(
        "--gateway-hosts",
        help="Processes the fleet's gateways run in, the vehicles split over them (bench.gateway_host); "
        "0: one per vehicle, as deployed.",
    ),
]
GatewayVision = Annotated[
    str,
    typer.Option(
        "--gateway-vision",
        help="With --gateway-hosts: their vision as one message per mocap frame (frame) or on each "
        "vehicle's own key (vehicle).",
    ),
]
Out = Annotated[Path, typer.Option("--out", "-o", help="Directory of the JSON results.")]
Docs = Annotated[
    bool | None,
    typer.Option(
        "--docs/--no-docs", help="Write the tables into docs/performance.md (default: full runs only)."
    ),
]
DocsFile = Annotated[Path, typer.Option("--docs-file", help="The document to update.")]
Rerender = Annotated[
    Path | None,
    typer.Option("--from", help="Re-render the tables (and docs, unless --no-docs) from a stored result."),
]


def _numbers(text: str, what: str, kind: type = float) -> tuple[Any, ...]:
    try:
        values = tuple(kind(x) for x in text.split(",") if x.strip())
    except ValueError:
        raise typer.BadParameter(f"{what}: expected comma-separated numbers, got {text!r}") from None
    if not values:
        raise typer.BadParameter(f"{what}: give at least one value")
    return values


def bench(
    part: Part = None,
    vehicles: Vehicles = None,
    rates: Rates = None,
    floor: Floor = None,
    duration: Duration = None,
    warmup: Warmup = None,
    quick: Quick = False,
    profile: Profile = False,
    realistic_vision: RealisticVision = 50.0,
    overload: Overload = None,
    peer_repeats: PeerRepeats = None,
    peer_duration: PeerDuration = None,
    hops: Hops = False,
    decimate: Decimate = None,
    vehicle_mode: VehicleMode = "",
    fleet: Fleet = None,
    growth: Growth = None,
    gateway_hosts: GatewayHosts = 0,
    gateway_vision: GatewayVision = "frame",
    out: Out = Path("bench-results"),
    docs: Docs = None,
    docs_file: DocsFile = Path("docs/performance.md"),
    rerender: Rerender = None,
) -> None:
    """Measure the arena: end-to-end latency, loss, vision rate, CPU and memory at 1 and 20 vehicles × 180 Hz
    (as deployed and overloaded too), a fleet of 50 as deployed and how the cost grows from 1 to 50, beside
    a bare Zenoh and a UDP chain of the same processes, the gateway beside its floors and MAVProxy, and
    per-stage costs."""
    from bench import run as bench_mod

    if rerender is not None:
        bench_mod.rerender(rerender, docs_file if docs is not False else None)
        return
    changes: dict[str, Any] = {
        "out_dir": out,
        "profile": profile,
        "hops": hops,
        "realistic_vision": realistic_vision if realistic_vision > 0 else None,
    }
    if part:
        changes["parts"] = tuple(part)
    if vehicles is not None:
        changes["vehicles"] = _numbers(vehicles, "--vehicles", int)
    if rates is not None:
        changes["rates"] = _numbers(rates, "--rates")
    if floor:
        changes["floors"] = tuple(floor)
    if decimate:
        changes["decimate"] = tuple(decimate)
    if vehicle_mode:
        changes["vehicle_mode"] = vehicle_mode
    if gateway_hosts:
        changes["gateway_hosts"] = gateway_hosts
        changes["gateway_vision"] = gateway_vision
    if fleet is not None:
        changes["fleet"] = fleet
    elif vehicles is not None:  # `-n 1` asks for one vehicle: the fleet of 50 only when asked for too
        changes["fleet"] = 0
    if growth is not None:
        changes["growth"] = tuple(n for n in _numbers(growth, "--growth", int) if n)
    elif vehicles is not None:  # likewise the growth table
        changes["growth"] = ()
    given = {
        "duration": duration,
        "warmup": warmup,
        "overload": overload,
        "peer_repeats": peer_repeats,
        "peer_duration": peer_duration,
    }
    changes.update({k: v for k, v in given.items() if v is not None})
    write_docs = (not quick) if docs is None else docs
    changes["docs"] = docs_file if write_docs else None
    options = bench_mod.BenchOptions.quick_options(**changes) if quick else bench_mod.BenchOptions(**changes)
    try:
        bench_mod.run(options)
    except bench_mod.BenchError as exc:
        typer.echo(f"error: {exc}", err=True)
        raise typer.Exit(2) from None


if __name__ == "__main__":
    typer.run(bench)
