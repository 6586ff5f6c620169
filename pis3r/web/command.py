"""``pis3r serve``: the web page on a local port."""

from __future__ import annotations

import ipaddress

import click


@click.command("serve")
@click.option("--host", default="127.0.0.1", show_default=True,
              help="Interface to listen on; anything but a loopback address exposes the page to the network.")
@click.option("--port", type=click.IntRange(0, 65535), default=8000, show_default=True)
@click.option("--workers", type=click.IntRange(1, 16), default=1, show_default=True,
              help="Stitch jobs run at the same time (each needs memory for its images).")
def serve_command(host, port, workers):
    """Serve the web page: drop photos, stitch, download the results (API docs at /docs)."""
    import uvicorn

    from pis3r.web.app import WebLimits, create_app

    try:
        loopback = ipaddress.ip_address(host).is_loopback
    except ValueError:
        loopback = host == "localhost"
    if not loopback:
        click.echo(f"pis3r: warning: listening on {host}: anyone who can reach it can upload photos", err=True)
    click.echo(f"pis3r: serving on http://{host}:{port}/  (API docs: /docs)", err=True)
    uvicorn.run(create_app(WebLimits(workers=workers)), host=host, port=port, log_level="warning")
