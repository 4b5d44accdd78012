"""``arena run ros2`` as docs/ros2.md gives it: the named config's vehicles appear to ROS 2 (rmw_zenoh tokens).

Each command line of the doc, with the doc's config replaced by one of free ports (vehicles d1 and d2 on
host ``sim``, or ``ground``), runs as the real console script; a test-only ROS 2 subscriber built from
rmw_zenoh's design (``tests/ros2_probe.py``) on the config's router finds the service's publishers
through their liveliness tokens: every vehicle's topics, or d1's alone with ``-v d1``; with
``--no-commands`` no ``goto``/``cmd_vel`` subscription.  Ctrl-C ends it with nothing left.
"""

from __future__ import annotations

from collections.abc import Callable, Iterator
from pathlib import Path

import pytest
import zenoh

from tests.helpers import free_port, wait_for
from tests.ros2_probe import Probe, open_session
from tests.typed.harness import Command, stops_cleanly

CONFIG = """
[arena]
name = "ros2-typed"
[zenoh]
connect = ["{ep}"]
router_listen = ["{ep}"]
[hosts.{host}]
services = ["router", "ros2"]
[vehicles.d1]
mavlink = "udpin:127.0.0.1:{p1}"
system_id = 1
[vehicles.d2]
mavlink = "udpin:127.0.0.1:{p2}"
system_id = 2
"""


@pytest.fixture
def probe_at() -> Iterator[Callable[[str], Probe]]:
    made: list[tuple[Probe, zenoh.Session]] = []

    def make(endpoint: str) -> Probe:
        session = open_session(endpoint, "client")
        probe = Probe(session)
        made.append((probe, session))
        return probe

    yield make
    for probe, session in made:
        probe.close()
        session.close()


@pytest.mark.covers(
    "arena run ros2",
    "arena run ros2 -c deploy/sim.toml --host sim",
    "arena run ros2 -c lab.toml --host ground -v d1 --no-commands",
)
@pytest.mark.parametrize(
    ("host", "extra", "vehicles", "commands"),
    [("sim", [], {"d1", "d2"}, True), ("ground", ["-v", "d1", "--no-commands"], {"d1"}, False)],
    ids=["sim-all-vehicles", "lab-d1-read-only"],
)
def test_run_ros2_as_the_doc_gives_it(
    tmp_path: Path,
    typed: Callable[..., Command],
    probe_at: Callable[[str], Probe],
    host: str,
    extra: list[str],
    vehicles: set[str],
    commands: bool,
) -> None:
    endpoint = f"tcp/127.0.0.1:{free_port()}"
    cfg = tmp_path / "arena.toml"
    cfg.write_text(CONFIG.format(ep=endpoint, host=host, p1=free_port(), p2=free_port()))
    router = typed("router", "-c", str(cfg), "--host", host)
    router.wait_line(r"routing on tcp/")
    probe = probe_at(endpoint)
    ros2 = typed("run", "ros2", "-c", str(cfg), "--host", host, *extra)
    wait_for(lambda: probe.nodes(), timeout=60, interval=0.2, what="the ros2 node's token")
    for v in vehicles:
        probe.find(f"/arena/{v}/pose", "MP", timeout=30)
    probe.find("/tf", "MP", timeout=30)
    topics = {e.topic for e in probe.endpoints("MP")}
    assert not {t for t in topics if t.startswith("/arena/") and t.split("/")[2] not in vehicles}, topics
    if commands:
        probe.find("/arena/d1/goto", "MS", timeout=30)
        probe.find("/arena/d2/cmd_vel", "MS", timeout=30)
    else:
        assert not [e for e in probe.endpoints("MS") if e.topic.startswith("/arena/")], probe.endpoints("MS")
    assert (
        stops_cleanly(ros2, [str(tmp_path / "arena.toml") + " --host " + host + " " + " ".join(extra)]) == 0
    )
    wait_for(lambda: not probe.nodes(), timeout=30, interval=0.2, what="the node's token gone after Ctrl-C")
    assert stops_cleanly(router, [str(tmp_path)]) == 0, router.output()
