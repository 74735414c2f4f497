"""`flakedb info FILE`: what is in a Fourier ``.bsdf`` or flakedb HDF5 BSDF file."""

import json

import click
import numpy as np

from flakedb.bsdf import BSDFFileError, open_bsdf
from flakedb.cli.errors import FlakedbError

#: Incident zenith angles [deg] (light arriving from above) at which the albedo is listed.
INFO_THETA_DEG = (0.0, 30.0, 45.0, 60.0, 75.0, 85.0)


def describe(path):
    """A JSON-able summary of the BSDF file at ``path`` (raises BSDFFileError when unreadable)."""
    b = open_bsdf(path)
    size = b.path.stat().st_size
    mu = np.cos(np.radians(INFO_THETA_DEG))
    albedo = b.albedo(mu)
    if b.kind == "bsdf":
        stored = "Y, R, B" if b.n_channels == 3 else "mono"
        full = b.n_nodes * b.n_nodes * b.n_channels * max(b.max_order, 1)
        fmt = f"Fourier .bsdf (layerlab / Mitsuba 0.6 / pbrt-v3), version {b.header['version']}, flags {b.header['flags']}"
    else:
        stored = ", ".join(b.channels)
        full = b.n_coeffs
        fmt = f"flakedb HDF5 BSDF, format version {b.metadata.get('h5_format_version')}"
    return {
        "file": str(b.path),
        "format": fmt,
        "size_bytes": size,
        "nodes": b.n_nodes,
        "quadrature_nodes": b.n_nodes - 2,
        "channels": b.n_channels,
        "stored_channels": stored,
        "eval_channels": list(b.channels),
        "max_order": b.max_order,
        "coefficients": b.n_coeffs,
        "coefficients_untruncated": full,
        "eta": b.eta,
        "alpha": list(b.alpha),
        "delta": b.delta,
        "metadata": b.metadata,
        "albedo": [{"theta_i_deg": t, "mu_i": float(m), "albedo": [float(x) for x in a]}
                   for t, m, a in zip(INFO_THETA_DEG, mu, albedo)],
        "albedo_sampling_channel_range": [float(np.min(b.albedo_nodes()[b.nodes != 0])),
                                          float(np.max(b.albedo_nodes()[b.nodes != 0]))],
    }


@click.command()
@click.argument("file", type=click.Path(dir_okay=False))
@click.option("--json", "as_json", is_flag=True, help="Print the summary as JSON.")
def info(file, as_json):
    """Describe a Fourier .bsdf or flakedb .h5 BSDF file: nodes, channels, orders, eta, alpha,
    the smooth coat's delta term, metadata, and the albedo (R + T) at a few incident angles."""
    try:
        d = describe(file)
    except BSDFFileError as e:
        raise FlakedbError(f"{e}\nflakedb info reads Fourier .bsdf files (SCATFUN) and flakedb HDF5 BSDF files.") from None
    if as_json:
        click.echo(json.dumps(d, indent=2, default=str))
        return
    echo = click.echo
    echo(f"file:          {d['file']} ({d['size_bytes']} bytes)")
    echo(f"format:        {d['format']}")
    echo(f"nodes:         {d['nodes']} ({d['quadrature_nodes']} quadrature nodes + 2 zero nodes)")
    echo(f"channels:      {d['channels']} (stored {d['stored_channels']}; eval returns {', '.join(d['eval_channels'])})")
    echo(f"max order:     {d['max_order']}")
    pct = 100.0 * d["coefficients"] / max(d["coefficients_untruncated"], 1)
    echo(f"coefficients:  {d['coefficients']} ({pct:.1f}% of {d['coefficients_untruncated']} untruncated)")
    echo(f"eta:           {d['eta']:g} (eta_below / eta_above)")
    echo(f"alpha:         {d['alpha'][0]:g}, {d['alpha'][1]:g}")
    delta = d["delta"]
    if delta is None:
        echo("delta term:    none (everything is in the table)")
    else:
        fields = ", ".join(f"{k}={v}" for k, v in delta.items() if k != "kind")
        echo(f"delta term:    {delta.get('kind')} ({fields}): first-surface mirror reflection, NOT in the table")
    if d["metadata"]:
        echo("metadata:")
        for k, v in d["metadata"].items():
            text = v if isinstance(v, str) else json.dumps(v)
            lines = text.split("\n")
            echo(f"  {k}: {lines[0]}")
            for ln in lines[1:]:
                echo(f"    {ln}")
    else:
        echo("metadata:      (none)")
    echo(f"albedo (R + T, light from above), per channel {', '.join(d['eval_channels'])}:")
    for row in d["albedo"]:
        vals = "  ".join(f"{x:.5f}" for x in row["albedo"])
        echo(f"  theta_i = {row['theta_i_deg']:4.0f} deg (mu_i = {row['mu_i']:.4f}):  {vals}")
    lo, hi = d["albedo_sampling_channel_range"]
    echo(f"sampling-channel albedo at the nodes (2 pi cdf[i][N-1]): {lo:.5f} … {hi:.5f}")
