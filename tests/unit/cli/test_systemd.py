"""``arena deploy systemd``: the units a host gets, their content, and systemd's own verdict on them."""

from __future__ import annotations

import re
import shutil
import subprocess
import sys
from pathlib import Path

import pytest
from typer.testing import CliRunner

from arena_common.cli import app
from arena_common.cli._deploy import ROUTER_UNIT, TEMPLATE_DIR, DeployError, render_systemd, write_units
from arena_common.core import config as config_mod
from arena_common.core.errors import ConfigError
from arena_common.core.services import SERVICES, by_name
from tests.helpers import REPO, open_lab

runner = CliRunner()
LAB = REPO / "deploy/lab.example.toml"
UNITS = "etc/systemd/system"


def test_every_template_exists_and_is_hardened() -> None:
    names = [ROUTER_UNIT] + [s.unit for s in SERVICES if s.config]
    for name in names:
        text = (TEMPLATE_DIR / name).read_text()
        for line in (
            "Restart=on-failure",
            "EnvironmentFile=/etc/arena/arena.env",
            "NoNewPrivileges=yes",
            "PrivateTmp=yes",
            "ProtectSystem=strict",
            "ProtectHome=read-only",
            "StandardOutput=journal",
            "PartOf=arena.target",
            "WantedBy=arena.target",
        ):
            assert re.search(rf"^{re.escape(line)}$", text, re.M), f"{name}: no {line}"
        assert re.search(r"^RestartSec=\d+", text, re.M), name
        assert re.search(
            r"^ExecStart=@PYTHON@ -m \S+ .*--config \$\{ARENA_CONFIG\} --host \$\{ARENA_HOST\}(@BUSARGS@)?$",
            text,
            re.M,
        )
        assert ("ReadWritePaths=" in text) == (name == "arena-recorder.service"), name
    assert "%i" in (TEMPLATE_DIR / "arena-gateway@.service").read_text()
    # Every template is a unit of the table of services (or the router's): none left from a renamed one.
    assert sorted(p.name for p in TEMPLATE_DIR.glob("*.service")) == sorted(names)
    assert (TEMPLATE_DIR / "arena.env").read_text().count("ARENA_") >= 2


def test_ground_host_units(tmp_path: Path) -> None:
    cfg = config_mod.load(open_lab(tmp_path))
    units = render_systemd(cfg, "ground", python=sys.executable, workdir=tmp_path, user="pilot")
    assert set(units.files) == {
        f"{UNITS}/arena-router.service",
        f"{UNITS}/arena-mocap.service",
        f"{UNITS}/arena-transform.service",
        f"{UNITS}/arena-recorder.service",
        f"{UNITS}/arena-downsampler@.service",
        f"{UNITS}/arena-gateway@.service",
        f"{UNITS}/arena.target",
        "etc/arena/arena.env",
    }
    for rel, text in units.files.items():
        assert not re.search(r"@[A-Z]+@", text), f"placeholder left in {rel}"
    mocap = units.files[f"{UNITS}/arena-mocap.service"]
    start = f"ExecStart={sys.executable} -m services.mocap_ingest --config ${{ARENA_CONFIG}}"
    start += " --host ${ARENA_HOST}"
    # The ground computer has an address: its peers listen there, for the other computers to reach them.
    assert f"{start} --listen tcp/192.168.1.20:0\n" in mocap
    assert "User=pilot" in mocap and f"WorkingDirectory={tmp_path.resolve()}" in mocap
    assert "After=network-online.target arena-router.service" in mocap
    # Names, modules and descriptions come from the table of services.
    assert f"Description=Flying Arena: {by_name('mocap').summary}\n" in mocap
    assert "SyslogIdentifier=arena-mocap\n" in mocap
    router = units.files[f"{UNITS}/arena-router.service"]
    assert (
        "-m arena_common.cli router --config" in router
        and "arena-router.service" not in router.split("[Service]")[0]
    )
    recorder = units.files[f"{UNITS}/arena-recorder.service"]
    assert "ReadWritePaths=-/var/lib/arena/recordings" in recorder  # the lab config's absolute directory
    gateway = units.files[f"{UNITS}/arena-gateway@.service"]
    assert "--vehicle %i" in gateway and "PrivateDevices" not in gateway  # the radio is a device
    assert f"Description=Flying Arena: {by_name('gateway').summary} (%i)\n" in gateway
    assert "SyslogIdentifier=arena-gateway-%i\n" in gateway
    target = units.files[f"{UNITS}/arena.target"]
    wants = re.search(r"^Wants=(.*)$", target, re.M)
    assert wants is not None
    assert wants[1].split() == [
        "arena-router.service",
        "arena-mocap.service",
        "arena-transform.service",
        "arena-recorder.service",
        "arena-downsampler@c3.service",
        "arena-gateway@c3.service",
    ]
    # The CPU share comes from the table too: the vision path goes first, the recorder yields.
    for unit, nice, weight in (
        (mocap, "-5", "300"),
        (router, "-5", "300"),
        (gateway, "-5", "300"),
        (units.files[f"{UNITS}/arena-transform.service"], "-5", "300"),
        (recorder, "10", "20"),
    ):
        service = unit.split("[Service]")[1]
        assert f"\nNice={nice}\nCPUWeight={weight}\n" in service, unit
    env = units.files["etc/arena/arena.env"]
    assert f"ARENA_CONFIG={(tmp_path / 'open-lab.toml').resolve()}\n" in env and "ARENA_HOST=ground\n" in env
    assert units.enable[-1] == "arena.target" and "arena-gateway@c3.service" in units.enable


def test_units_of_the_locked_down_lab(tmp_path: Path) -> None:
    """The shipped recipe: every service a client of the router (no listener), the transform decimating."""
    cfg = config_mod.load(LAB)
    cc1 = render_systemd(cfg, "cc1", workdir=tmp_path)
    assert sorted(cc1.files) == sorted(
        [f"{UNITS}/arena-gateway@.service", f"{UNITS}/arena.target", "etc/arena/arena.env"]
    )
    assert (
        "--vehicle %i --config ${ARENA_CONFIG} --host ${ARENA_HOST}\n"
        in cc1.files[f"{UNITS}/arena-gateway@.service"]
    )
    ground = render_systemd(cfg, "ground", workdir=tmp_path).files
    starts = [
        line
        for name, text in ground.items()
        if name.endswith(".service") and "router" not in name
        for line in text.splitlines()
        if line.startswith("ExecStart=")
    ]
    assert starts and not [line for line in starts if "--listen" in line or "--mode peer" in line]


def test_companion_host_units_and_errors(tmp_path: Path) -> None:
    cfg = config_mod.load(open_lab(tmp_path))
    units = render_systemd(cfg, "cc1", workdir=tmp_path)
    assert sorted(units.files) == sorted(
        [
            f"{UNITS}/arena-downsampler@.service",
            f"{UNITS}/arena-gateway@.service",
            f"{UNITS}/arena.target",
            "etc/arena/arena.env",
        ]
    )
    assert (
        "Wants=arena-downsampler@c1.service arena-gateway@c1.service\n"
        in units.files[f"{UNITS}/arena.target"]
    )
    gateway = units.files[f"{UNITS}/arena-gateway@.service"]
    assert (
        "--vehicle %i --config ${ARENA_CONFIG} --host ${ARENA_HOST} --listen tcp/192.168.1.31:0\n" in gateway
    )
    sim_units = render_systemd(config_mod.load(REPO / "deploy/sim.toml"), "sim", workdir=tmp_path).files
    assert "--host ${ARENA_HOST}\n" in sim_units[f"{UNITS}/arena-mocap.service"]  # no address: loopback
    # A relative recordings directory resolves in the working directory.
    sim = config_mod.load(REPO / "deploy/sim.toml")
    assert not any("recorder" in f for f in render_systemd(sim, "sim", workdir=tmp_path).files)
    with pytest.raises(ConfigError, match=r"known hosts: ground, cc1, cc2"):
        render_systemd(cfg, "nope")
    empty = tmp_path / "empty.toml"
    empty.write_text("[hosts.idle]\n")
    with pytest.raises(DeployError, match="host 'idle' runs no service and no vehicle"):
        render_systemd(config_mod.load(empty), "idle")


def test_cli_writes_units_under_prefix(tmp_path: Path) -> None:
    lab = str(open_lab(tmp_path))
    res = runner.invoke(app, ["deploy", "systemd", lab, "--host", "cc2", "--prefix", str(tmp_path)])
    assert res.exit_code == 0, res.output
    assert (tmp_path / UNITS / "arena-gateway@.service").is_file()
    assert "ARENA_HOST=cc2" in (tmp_path / "etc/arena/arena.env").read_text()
    assert (
        "sudo systemctl enable arena-downsampler@c2.service arena-gateway@c2.service arena.target"
        in res.output
    )
    assert "sudo systemctl start arena.target" in res.output
    bad = runner.invoke(app, ["deploy", "systemd", lab, "--host", "nope", "--prefix", str(tmp_path)])
    assert bad.exit_code == 2 and "known hosts: ground, cc1, cc2" in bad.output


def _verify(unit_dir: Path, *units: str) -> subprocess.CompletedProcess[str]:
    return subprocess.run(
        ["systemd-analyze", "verify", *units],
        env={"SYSTEMD_UNIT_PATH": f"{unit_dir}:", "PATH": "/usr/bin:/bin:/usr/sbin:/sbin"},
        capture_output=True,
        text=True,
        timeout=60,
    )


@pytest.mark.skipif(shutil.which("systemd-analyze") is None, reason="systemd-analyze is not installed here")
def test_systemd_analyze_verify(tmp_path: Path) -> None:
    """systemd's own checker accepts every generated unit without a single warning about them."""
    cfg = config_mod.load(open_lab(tmp_path))
    write_units(render_systemd(cfg, "ground", workdir=tmp_path), tmp_path)
    unit_dir = tmp_path / UNITS
    names = [
        "arena-router.service",
        "arena-mocap.service",
        "arena-transform.service",
        "arena-recorder.service",
        "arena-downsampler@c3.service",
        "arena-gateway@c3.service",
        "arena.target",
    ]
    res = _verify(unit_dir, *names)
    complaints = [line for line in (res.stdout + res.stderr).splitlines() if "arena" in line]
    assert res.returncode == 0 and not complaints, res.stdout + res.stderr
    # The checker does catch a broken unit here (so the pass above means something).
    broken = unit_dir / "arena-broken.service"
    broken.write_text(
        (unit_dir / "arena-mocap.service").read_text().replace(sys.executable, "/nonexistent/python")
    )
    res = _verify(unit_dir, "arena-broken.service")
    assert res.returncode != 0 and "/nonexistent/python" in res.stdout + res.stderr
