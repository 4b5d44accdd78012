"""Benchmarks of the arena (``make bench``, ``python -m bench``): not part of the installed runtime.

What each module measures, or does for the others, from the command down:

- ``__main__`` — the command line;
- ``run`` — one run: the parts asked for, their tables, the JSON result and docs/performance.md;
- ``pipeline`` — the real vision pipeline end to end, as processes on loopback: latency, loss, vision rate,
  CPU and memory of every process;
- ``floor_run`` — the same process topology with relays that only move bytes, over Zenoh or UDP (the
  relays and the frame source: ``floor``);
- ``peer`` — the gateway beside its floors (``forwarders``) and MAVProxy, forwarding one vision stream;
- ``micro`` — what each step of the pipeline costs in one process;
- ``idle`` — where one per-vehicle process's idle memory and CPU go;
- ``matching`` — each ODOMETRY matched to its frame, wire sizes; ``feeds`` — the harness's Zenoh side;
  ``harness`` — kernel-stamped sockets, child processes, CPU and memory, percentiles;
- ``targets`` — the performance targets judged from a result; ``report`` — its tables and the generated
  part of docs/performance.md; ``flames`` — before/after flame-graph summaries of two ``--profile`` runs.
"""
