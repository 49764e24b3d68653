"""The HTML report of a diagnosis: one self-contained page (figures inlined as base64 PNG)."""

from __future__ import annotations

import base64
import html
import io

import matplotlib

matplotlib.use("Agg")
import matplotlib.pyplot as plt
import numpy as np

from calib.joints import SDK_JOINT_NAMES
from sim2real.candidates import UNITS
from sim2real.diagnose import Diagnosis

__all__ = ["render_report"]

_CSS = """
body{font-family:system-ui,sans-serif;max-width:1100px;margin:2em auto;color:#222;line-height:1.4}
table{border-collapse:collapse;margin:1em 0}td,th{border:1px solid #ccc;padding:4px 8px;
text-align:left}th{background:#f3f3f3}tr.chosen{background:#e8f6e8}.big{font-size:1.3em}
.bad{color:#b00}.good{color:#070}img{max-width:100%}code{background:#f4f4f4;padding:0 3px}
"""


def _png(fig) -> str:
    buf = io.BytesIO()
    fig.savefig(buf, format="png", dpi=90, bbox_inches="tight")
    plt.close(fig)
    return '<img alt="figure" src="data:image/png;base64,' + \
        base64.b64encode(buf.getvalue()).decode("ascii") + '">'


def _bars(ax, before: dict, after: dict, title: str) -> None:
    names = list(before)
    x = np.arange(len(names))
    ax.bar(x - 0.2, [before[n] for n in names], 0.4, label="before (nominal sim)")
    if after:
        ax.bar(x + 0.2, [after.get(n, 0.0) for n in names], 0.4, label="after (held out)")
    ax.set_xticks(x, names, rotation=60 if len(names) > 6 else 0, ha="right" if len(names) > 6
                  else "center", fontsize=8)
    ax.set_title(title, fontsize=10)
    ax.set_ylabel("normalised gap")


def _where_figure(d: Diagnosis) -> str:
    # before and after on the same (held-out) windows when there is an after
    w, wa = d.where_heldout or d.where, d.where_after
    fig, axes = plt.subplots(2, 3, figsize=(13, 7))
    _bars(axes[0, 0], w["joints"], wa.get("joints", {}), "per joint")
    _bars(axes[0, 1], w["legs"], wa.get("legs", {}), "per leg")
    _bars(axes[0, 2], w["sensors"], wa.get("sensors", {}), "per sensor")
    _bars(axes[1, 0], w["phases"], wa.get("phases", {}), "per phase")
    _bars(axes[1, 1], w["bands"], wa.get("bands", {}), "per frequency band (joints)")
    share = d.screening.get("torque_share", {})
    ax = axes[1, 2]
    ax.bar(np.arange(12), [share.get(n, 0.0) for n in SDK_JOINT_NAMES], color="tab:gray")
    ax.set_xticks(np.arange(12), SDK_JOINT_NAMES, rotation=60, ha="right", fontsize=8)
    ax.set_title("share of the unexplained torque", fontsize=10)
    axes[0, 0].legend(fontsize=8)
    fig.tight_layout()
    return _png(fig)


def _overlay_figure(d: Diagnosis) -> str:
    rec, nom, aft = d.recording, d.nominal, d.after
    jg = d.where["joints"]
    joint = max(jg, key=jg.get)
    j = SDK_JOINT_NAMES.index(joint)
    held = d.heldout_mask if d.heldout_mask is not None else nom.mask
    idx = np.nonzero(held)[0]
    if idx.size == 0:
        idx = np.arange(rec.n)
    # the first two held-out windows
    breaks = np.nonzero(np.diff(idx) > 1)[0]
    stop = idx[breaks[1]] + 1 if breaks.size > 1 else idx[-1] + 1
    sl = slice(max(idx[0] - 1, 0), stop)
    t = rec.t[sl]
    hm = held[sl]

    def only_held(x):
        return np.where(hm[:, None] if x.ndim == 2 else hm, x, np.nan)

    nom_q, nom_dq, nom_g = only_held(nom.q[sl]), only_held(nom.dq[sl]), only_held(nom.gyro[sl])
    if aft is not None:
        aft_q, aft_dq, aft_g = only_held(aft.q[sl]), only_held(aft.dq[sl]), only_held(aft.gyro[sl])
    show_imu = d.where["sensors"]["body_gyro"] > d.where["sensors"]["encoders"]
    fig, axes = plt.subplots(3 if show_imu else 2, 1, figsize=(12, 8 if show_imu else 6),
                             sharex=True)
    for ax, rec_x, nom_x, aft_x, lab in (
            (axes[0], rec.q[sl, j], nom_q[:, j], None if aft is None else aft_q[:, j],
             f"q {joint} (rad)"),
            (axes[1], rec.dq[sl, j], nom_dq[:, j], None if aft is None else aft_dq[:, j],
             f"dq {joint} (rad/s)")):
        ax.plot(t, rec_x, "k", lw=1.2, label="recording")
        ax.plot(t, nom_x, "tab:red", lw=1, label="sim, nominal")
        if aft_x is not None and d.significant_gap:
            ax.plot(t, aft_x, "tab:green", lw=1, ls="--", label="sim + chosen effects")
        ax.set_ylabel(lab)
    if show_imu:
        ax = axes[2]
        for k, c in enumerate("xyz"):
            ax.plot(t, rec.base_gyro[sl, k], lw=1, label=f"recorded gyro {c}")
            ax.plot(t, nom_g[:, k], lw=1, ls=":", label=f"sim gyro {c}")
            if aft is not None and d.significant_gap:
                ax.plot(t, aft_g[:, k], lw=1, ls="--", label=f"sim + effects gyro {c}")
        ax.set_ylabel("body gyro (rad/s)")
        ax.legend(fontsize=7, ncol=3)
    axes[0].legend(fontsize=8)
    axes[-1].set_xlabel("time (s); held-out windows, each re-synchronised at its start")
    fig.tight_layout()
    return _png(fig)


def _fmt(v: float) -> str:
    return f"{v:.4g}"


def render_report(d: Diagnosis) -> str:
    """The report page (a str of HTML) for a :class:`Diagnosis`."""
    rec = d.recording
    e = html.escape
    verdict = ("<span class='bad'>significant gap</span>" if d.significant_gap
               else "<span class='good'>no significant gap</span>")
    red = 100 * (1 - d.gap_after / d.gap_before) if d.gap_before > 0 else 0.0
    chosen = [f for f in d.effects if f.chosen]
    rows = []
    for i, f in enumerate(d.effects):
        params = "<br>".join(
            f"{e(k)} = {_fmt(v)} {e(UNITS.get(k, ''))} [{_fmt(f.ci[k][0])}, {_fmt(f.ci[k][1])}]"
            for k, v in f.parameters.items())
        r = 100 * (1 - f.gap_after_heldout / d.gap_before) if d.gap_before > 0 else 0.0
        rows.append(
            f"<tr class='{'chosen' if f.chosen else ''}'><td>{i + 1}</td><td>{e(f.name)}</td>"
            f"<td>{e(', '.join(f.location))}</td><td>{params}</td><td>{f.k}</td>"
            f"<td>{f.gap_after_heldout:.4f}</td><td>{r:.0f} %</td><td>{f.bic:.1f}</td>"
            f"<td>{'chosen' if f.chosen else ''}</td></tr>")
    scr = d.screening
    ch_rows = "".join(
        f"<tr><td>{e(n)}</td><td>{v:.4f}</td><td>{d.where_after.get('channels', {}).get(n, float('nan')):.4f}</td></tr>"
        for n, v in sorted((d.where_heldout or d.where)["channels"].items(),
                           key=lambda kv: -kv[1])[:12])
    chosen_txt = " + ".join(f"{f.name} at {', '.join(f.location)}" for f in chosen) or "none"
    parts = [
        "<!DOCTYPE html><html><head><meta charset='utf-8'>",
        f"<title>Sim-to-real diagnosis: {e(rec.source or 'recording')}</title>",
        f"<style>{_CSS}</style></head><body>",
        "<h1>Sim-to-real diagnosis</h1>",
        (f"<p>Recording <code>{e(rec.source)}</code>: {rec.duration:.1f} s, mount "
        f"<b>{e(rec.mount)}</b>, {rec.n} state samples, {rec.cmd_t.size} commands. "
        f"Diagnosed in {d.seconds:.1f} s.</p>"),
        (f"<p class='big'>Verdict: {verdict}. Chosen effect(s): <b>{e(chosen_txt)}</b>.<br>"
        f"Held-out gap {d.gap_before:.4f} &rarr; {d.gap_after:.4f} ({red:.0f} % smaller).</p>"),
        ("<p>The gap is the noise-corrected RMS of the replay residuals, each channel divided "
        "by the spread of its recorded signal (0.1 = 10 % of the motion); the replay restarts "
        "from the recorded state every window, and one window in three is held out of every "
        "fit. Method: <code>docs/sim2real.md</code>.</p>"),
        "<h2>Effects, most likely first</h2>",
        "<table><tr><th>#</th><th>effect</th><th>location</th><th>parameters [95 % CI]</th>"
        "<th>k</th><th>held-out gap after</th><th>reduction</th><th>BIC (held out)</th>"
        "<th></th></tr>" + "".join(rows) + "</table>",
        (f"<p>Screening: joint-channel gap {scr['gap_joints']:.4f}, body-IMU gap "
        f"{scr['gap_imu']:.4f}; the unexplained torque points to <b>{e(scr['location'])}</b>."
        "</p>"),
        "<h2>Where the gap lies</h2>", _where_figure(d),
        "<h3>Largest channels</h3><table><tr><th>channel</th><th>gap before</th>"
        "<th>after (held out)</th></tr>" + ch_rows + "</table>",
        "<h2>Before / after (held-out windows)</h2>", _overlay_figure(d),
        "</body></html>",
    ]
    return "\n".join(parts)
