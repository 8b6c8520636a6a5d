"""``psdcal inspect``: what a recording holds, before demodulating it (a thin layer over
:mod:`psdcal.signal.inspect`)."""
from __future__ import annotations

import click

from psdcal.cli import cli


@cli.command("inspect")
@click.argument("recording", type=click.Path(dir_okay=False))
@click.option("--rate-hz", type=float, help="Sampling rate (when the file does not carry one).")
@click.option("--channels", help="Names of vx1,vx2,vy1,vy2 in the file (CSV columns, HDF5 datasets, TDMS channels).")
@click.option("--dataset", help="HDF5: an (n, 4) dataset.")
@click.option("--group", help="HDF5 or TDMS group.")
@click.option("--carrier-hz", "carriers", type=float, multiple=True,
              help="Carrier(s) you mean to demodulate: checked against the measured ones (repeatable).")
@click.option("--window-s", type=float, default=0.01, show_default=True,
              help="Demodulation window the carrier check assumes.")
@click.option("--max-samples", type=int, default=1 << 18, show_default=True,
              help="Samples per channel read from the start of the recording.")
@click.option("--min-snr-db", type=float, default=20.0, show_default=True,
              help="A spectral peak this far above the noise floor counts as a carrier (side-bands of on/off "
                   "keying, 20 dB below a carrier within 50 % of it, are not listed).")
@click.option("--min-snr", type=float, default=10.0, show_default=True,
              help="TDM preview: a window is 'on' above this many sigma.")
def inspect_command(recording, rate_hz, channels, dataset, group, carriers, window_s, max_samples, min_snr_db,
                    min_snr):
    """Show what RECORDING holds: channels, carriers found, TDM segments.

    \b
    Prints the carriers found (frequency, SNR per channel, amplitude per
    channel), checks each --carrier-hz against them (a carrier off its
    measured frequency inflates every sigma), and previews the time-
    multiplexed segments of the strongest (or first asked) carrier with the
    on-times, dark gaps and the demodulation window 'locate --tdm' would pick.
    \b
    Example:
      psdcal inspect rec.npy --rate-hz 100000 --carrier-hz 1000
    Exit status 0 when every asked carrier is where it was asked, 1 otherwise.
    """
    import math

    import numpy as np

    from psdcal.cli.locate_cmd import _channels
    from psdcal.errors import InputError
    from psdcal.signal.inspect import check_carrier, choose_tdm_window, find_carriers, measure_carrier, read_prefix, scan_tdm
    from psdcal.signal.recording import open_recording

    if max_samples < 64:
        raise InputError(f"--max-samples must be at least 64, got {max_samples}", field="max_samples")
    rec = open_recording(recording, rate_hz, channels=_channels(channels), dataset=dataset, group=group)
    x = read_prefix(rec, max_samples)
    n = x.shape[1]
    if n < 64:
        raise InputError(f"too few samples to inspect ({n}; at least 64)", path=rec.path)
    names = ("vx1", "vx2", "vy1", "vy2")
    total = "" if rec.n_samples is None else f" of {rec.n_samples}"
    click.echo(f"{rec.path}: {rec.kind}, {rec.rate_hz:g} Hz, {n}{total} samples read ({n / rec.rate_hz:.6g} s)")
    click.echo("channel     mean        std         min         max")
    for c, nm in enumerate(names):
        v = x[c]
        click.echo(f"{nm:<8}{v.mean():>11.4g} {v.std():>11.4g} {v.min():>11.4g} {v.max():>11.4g}")
    found = find_carriers(x, rec.rate_hz, min_snr_db=min_snr_db)
    if not found:
        click.echo(f"carriers: none above {min_snr_db:g} dB (DC or unmodulated signal?)")
    else:
        click.echo(f"carriers (resolution {found[0].resolution_hz:.3g} Hz):")
        click.echo("  freq_hz        snr_db vx1/vx2/vy1/vy2          amplitude vx1/vx2/vy1/vy2")
        for c in found:
            snr = "/".join(f"{v:.0f}" for v in c.snr_db)
            amp = "/".join(f"{v:.3g}" for v in c.amplitude)
            click.echo(f"  {c.freq_hz:<14.7g} {snr:<26} {amp}")
    f0 = carriers[0] if carriers else (found[0].freq_hz if found else None)
    scan = scan_tdm(x, rec.rate_hz, f0, min_snr=min_snr) if f0 is not None else None
    # one carrier in bursts (time multiplexing, blinking): its spectral peak may be a keying side-band,
    # the carrier is measured from the phase slope inside the bursts instead
    tdm = len(carriers) == 1 and scan is not None and len(scan.segments) > 1
    bad = 0
    for f in carriers:
        chk = check_carrier(f, measure_carrier(x, rec.rate_hz, f, tdm=tdm, min_snr=min_snr), window_s, tdm=tdm)
        how = " in the bursts" if chk.measured is not None and math.isfinite(chk.measured.precision_hz) else ""
        if chk.ok:
            click.echo(f"check {f:g} Hz: ok (measured{how} {chk.measured.freq_hz:.7g} Hz, "
                       f"sigma x{chk.sigma_inflation:.3g})")
        else:
            bad += 1
            click.echo(f"check {f:g} Hz: WARNING {chk.message}")
    if scan is not None:
        click.echo(f"TDM preview at {f0:.7g} Hz ({scan.window_s * 1e3:.3g} ms windows): {len(scan.segments)} segments")
        for s, on in list(zip(scan.segments, scan.on_s))[:20]:
            r = s.amplitude / s.amplitude.sum() if s.amplitude.sum() != 0 else s.amplitude * np.nan
            click.echo(f"  {s.emitter:>3}  {s.t_start_s:9.4f}-{s.t_end_s:9.4f} s  on {on * 1e3:7.3g} ms  "
                       f"ratios {'/'.join(f'{v:.3f}' for v in r)}")
        if len(scan.segments) > 20:
            click.echo(f"  ... {len(scan.segments) - 20} more")
        if len(scan.segments):
            gaps = scan.gap_s
            g = f", dark gaps {gaps.min() * 1e3:.3g}-{gaps.max() * 1e3:.3g} ms" if gaps.size else ""
            click.echo(f"  on-times {scan.on_s.min() * 1e3:.3g}-{scan.on_s.max() * 1e3:.3g} ms{g}; "
                       f"locate --tdm would use a {choose_tdm_window(scan, f0) * 1e3:.3g} ms window")
    if bad:
        raise _CarrierOff(f"{bad} asked carrier(s) not where they were asked (see the WARNING lines)")


class _CarrierOff(click.ClickException):
    """Exit status 1: the recording was read, but a carrier is off."""

    exit_code = 1
