"""``arena security init|check|rules``: the lab's credentials, checked, and the router's access rules.

``arena security init lab.toml`` makes what the config's ``[security]`` table names: the lab CA, one
certificate per host (CN = host name) for mutual TLS, and/or one password per host with the router's
user file — every private key and password readable by its owner only.  ``arena security check`` says,
per host, whether what it needs is there and sound; ``arena security rules`` prints the router's access
rules (deny by default) as Zenoh JSON.
"""

from __future__ import annotations

import json
from pathlib import Path
from typing import Annotated

import typer

from arena_common.bus import pki, security
from arena_common.cli._globals import config as global_config
from arena_common.core.config import ArenaConfig

app = typer.Typer(help="The lab's credentials and access rules (docs/safety.md §3.3).", no_args_is_help=True)

ConfigArg = Annotated[
    Path | None, typer.Argument(help="Arena config file (or --config).", show_default=False)
]
FILES = ("ca", "cert", "key", "users_file", "password_file")


def _folder(cfg: ArenaConfig, directory: Path | None) -> Path:
    """Where the credentials go: ``--dir``, else the folder the config's ``[security]`` paths name."""
    if directory is not None:
        return directory
    spec = cfg.security
    for template in (spec.ca, spec.cert, spec.users_file, spec.password_file):
        if template:
            return Path(security.resolve(cfg, template, "x")).parent
    return Path(cfg.path).resolve().parent / "secrets"


def _names_fit(cfg: ArenaConfig, folder: Path) -> list[str]:
    """Config paths that would not find what ``init`` writes into ``folder`` (named, for the user)."""
    spec = cfg.security
    expected = {
        "ca": folder / "ca.pem",
        "cert": folder / "{host}.pem",
        "key": folder / "{host}.key",
        "users_file": folder / "users.txt",
        "password_file": folder / "{host}.password",
    }
    wrong = []
    for name in FILES:
        template = getattr(spec, name)
        if template and Path(security.resolve(cfg, template, "{host}")) != expected[name]:
            wrong.append(f"security.{name} = {template!r} (init writes {expected[name]})")
    return wrong


def init(
    config: ConfigArg = None,
    directory: Annotated[
        Path | None, typer.Option("--dir", help="Folder for the credentials (default: the config's).")
    ] = None,
    force: Annotated[bool, typer.Option("--force", help="Replace an existing lab CA and passwords.")] = False,
) -> None:
    """Make the lab CA, each host's certificate and each host's password, as the config's [security] names."""
    cfg = global_config(path=config)
    folder = _folder(cfg, directory).resolve()
    spec = cfg.security
    wrong = _names_fit(cfg, folder)
    if wrong:
        typer.echo(f"error: {cfg.path}: " + "; ".join(wrong), err=True)
        raise typer.Exit(2)
    tls = spec.tls or not spec.users_file  # with no [security] yet, mutual TLS (the recommended kind)
    try:
        if tls:
            addresses = {name: h.address for name, h in cfg.hosts.items()}
            pki.init_lab(folder, cfg.arena.name, addresses, spec.observers, force=force)
        if spec.users_file or not tls:
            if force:
                for p in folder.glob("*.password"):
                    p.unlink()
            security.make_credentials(cfg, folder)
    except (pki.PkiError, OSError) as exc:
        typer.echo(f"error: {exc}", err=True)
        raise typer.Exit(2) from None
    typer.echo(f"lab credentials in {folder} (private keys and passwords: owner only):")
    for p in sorted(folder.iterdir()):
        typer.echo(f"  {p.name:28s} {oct(p.stat().st_mode & 0o777)}")
    if not spec.enabled:
        typer.echo("\nAdd to the config (then copy each host's files to it; the CA key stays here):\n")
        typer.echo(
            "[security]\nenabled = true\ntls = true\nmtls = true\n"
            f'ca = "{folder}/ca.pem"\ncert = "{folder}/{{host}}.pem"\nkey = "{folder}/{{host}}.key"\n'
            f"command_hosts = [{', '.join(repr(h) for h in list(cfg.hosts)[:1])}]"
        )
    typer.echo(
        f"\nEach host needs ca.pem and its own <host>.pem/<host>.key; then: arena security check {cfg.path}"
    )


def check(
    config: ConfigArg = None,
    host: Annotated[str | None, typer.Option("--host", help="Check one host only.")] = None,
) -> None:
    """Check every host's credentials: present, owner-only secrets, certificates of the lab CA, rules valid."""
    cfg = global_config(path=config)
    spec = cfg.security
    if not spec.enabled:
        what = "insecure = true: anyone on the network" if spec.insecure else "loopback only"
        typer.echo(f"{cfg.path}: security is off ({what})")
        raise typer.Exit(0 if not spec.insecure else 1)
    problems: list[str] = []
    hosts = [host] if host else list(cfg.hosts)
    for h in hosts:
        try:
            if "router" in cfg.host(h).services:
                security.router_settings(cfg, spec, h)
            security.session_settings(cfg, spec, h)
        except security.SecurityError as exc:
            problems.append(f"{h}: {exc}")
            continue
        if spec.tls and spec.mtls:
            ca = Path(security.resolve(cfg, spec.ca, h))
            cert, key = (Path(security.resolve(cfg, t, h)) for t in (spec.cert, spec.key))
            problems += [f"{h}: {p}" for p in pki.check_certificate(ca, cert, key, h)]
    for p in problems:
        typer.echo(f"error: {p}", err=True)
    if problems:
        raise typer.Exit(1)
    kinds = " and ".join(
        k for k, on in (("mutual TLS", spec.tls and spec.mtls), ("passwords", bool(spec.users_file))) if on
    )
    typer.echo(
        f"{cfg.path}: ok — {len(hosts)} host(s) with {kinds or 'no identity'}; access rules deny by default"
    )


def rules(config: ConfigArg = None) -> None:
    """Print the router's access rules for this config (Zenoh JSON; deny by default)."""
    cfg = global_config(path=config)
    try:
        typer.echo(json.dumps(security.access_control(cfg, cfg.security), indent=2))
    except security.SecurityError as exc:
        typer.echo(f"error: {exc}", err=True)
        raise typer.Exit(2) from None


def register(root: typer.Typer) -> None:
    """Add ``arena security`` to ``root``."""
    app.command("init")(init)
    app.command("check")(check)
    app.command("rules")(rules)
    root.add_typer(app, name="security")
