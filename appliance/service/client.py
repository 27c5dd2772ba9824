"""``scan3d status``, ``scan3d trigger`` and ``scan3d tune`` (with a service running): clients of the control
socket."""

from __future__ import annotations

from pathlib import Path
from typing import Any

from appliance.config import load_config
from appliance.config.schema import ServiceConfig
from appliance.errors import ApplianceError, ConfigError
from appliance.service.control import dumps_json, request

STATUS_TIMEOUT_S = 10.0
TRIGGER_WAIT_TIMEOUT_S = 660.0
TUNE_TIMEOUT_S = 200.0  # the service's probe (up to its TUNE_TIMEOUT_S) and the apply's reload


def socket_for(config: Path | None, socket: Path | None) -> Path:
    """The control socket: ``socket`` when given, else the config's ``service.control_socket``."""
    if socket is not None:
        return Path(socket)
    if config is not None and Path(config).exists():
        try:
            return Path(load_config(config).service.control_socket)
        except ConfigError:
            pass  # a broken file being edited: the running service still uses its old socket path
    return ServiceConfig().control_socket


_CONTROL_CHARS = {c: "?" for c in (*range(0x20), 0x7F, *range(0x80, 0xA0)) if c != 0x0A}


def _shown(text: str) -> str:
    """A reply's text as the terminal shows it: control characters (escape sequences) printed as '?', not obeyed."""
    return text.translate(_CONTROL_CHARS)


def _ms(v: Any) -> str:
    return f"{float(v):.0f}" if isinstance(v, (int, float)) else "?"


def _uptime(s: float) -> str:
    s = int(s)
    d, s = divmod(s, 86400)
    h, s = divmod(s, 3600)
    m, s = divmod(s, 60)
    return f"{d}d {h}h {m:02d}m" if d else f"{h}h {m:02d}m {s:02d}s"


def format_status(st: dict[str, Any]) -> str:
    """One screen for a person: state, hardware, share, last scans with timings, the fault and what to do."""
    lines = []
    state = str(st.get("state", "?")).upper()
    head = f"scan3d {st.get('serial', '')} (version {st.get('version', '?')}): {state}"
    if st.get("state") in ("starting", "fault"):
        head += f" [{st.get('phase')}]"
    if st.get("detail"):
        head += f" — {st['detail']}"
    mem = f", RSS {float(st['rss_mb']):.0f} MB" if st.get("rss_mb") else ""
    lines.append(f"{head}   (up {_uptime(float(st.get('uptime_s', 0)))}{mem})")
    cfg = st.get("config", {})
    lines.append(f"config    {cfg.get('path')} (loaded {cfg.get('loaded_utc')})")
    if cfg.get("error"):
        first = str(cfg["error"]).splitlines()
        lines.append("          REJECTED edit (the last good configuration keeps running):")
        lines.extend(f"            {x}" for x in first[:4])
    if st.get("sequence"):
        lines.append(f"sequence  {st['sequence']}")
    lines.append("hardware")
    for d in st.get("devices", []):
        label = f"{d['role']} {d['name']}" if d["role"] == "camera" else d["role"]
        ok = "ok   " if d["ok"] else "FAULT"
        lines.append(f"  {label:<16} {d['backend']:<17} {ok}  {d['detail']}"[:160])
    sh = st.get("share", {})
    if sh:
        avail = "available" if sh.get("available") else f"UNAVAILABLE: {sh.get('problem')}"
        free = f", {sh['free_mb']:.0f} MB free" if "free_mb" in sh else ""
        lines.append(f"share     {sh.get('directory')}: {avail}{free}")
        lines.append(f"spool     {sh.get('spool_directory')}: {sh.get('spooled_scans', 0)} scan(s) waiting, "
                     f"{sh.get('spool_mb', 0)} MB, {sh.get('spool_dropped', 0)} dropped by retention")
    c = st.get("counters", {})
    lines.append(f"counters  scans {c.get('scans_done', 0)} done, {c.get('scans_failed', 0)} failed, "
                 f"{c.get('spooled', 0)} spooled; triggers {c.get('triggers', 0)} "
                 f"({c.get('triggers_refused', 0)} refused, {c.get('triggers_queued', 0)} queued, "
                 f"{st.get('queue_length', 0)} waiting); reloads {c.get('reloads', 0)} "
                 f"({c.get('reloads_rejected', 0)} rejected)")
    health = st.get("calibration_health") or {}
    if health:
        lines.append(f"calibration {health.get('status', '?')} (scan {health.get('scan_id', '?')}): "
                     f"{health.get('reason', '')}"[:200])
    scans = st.get("last_scans", [])
    lines.append("last scans" if scans else "last scans: none yet")
    for r in list(reversed(scans))[:5]:
        if r["ok"]:
            t = r.get("timings_ms", {})
            lines.append(f"  {r['scan_id']}  {r['location']:<5} {r['points']:>8} pts  "
                         f"scan {_ms(t.get('scan_ms'))} ms (capture {_ms(t.get('capture_ms'))}, "
                         f"reconstruct {_ms(t.get('reconstruct_ms'))}, write {_ms(t.get('write_ms'))}); "
                         f"trigger to file {_ms(t.get('trigger_to_file_ms'))} ms")
        else:
            lines.append(f"  {r['scan_id'] or '(refused)'}  FAILED ({r['trigger']}): {r['error']}"[:200])
    last_ok = next((r for r in reversed(scans) if r.get("ok")), None)
    if last_ok is not None:
        lines.extend(scan_findings_lines(last_ok))
    err = st.get("last_error")
    if err:
        lines.append(f"last error  {err['time_utc']} [{err['where']}]")
        lines.append(f"  {err['message']}"[:400])
        lines.append(f"  what to do: {err['advice']}")
    return "\n".join(lines)


def _pct(v: Any) -> str:
    return f"{100 * float(v):.1f} %" if isinstance(v, (int, float)) else "?"


def scan_findings_lines(rec: dict[str, Any]) -> list[str]:
    """Why the pixels of a scan have no point (per camera the reasons' shares of the image, largest first), the
    share of the image whose two copies of the pattern were taken apart, the share of the pixels both cameras see
    that got a point (camera-camera), its exposures and what each pass gave, and its plain-words warnings: lines
    for ``scan3d status``."""
    out: list[str] = []
    reasons = rec.get("reasons") or {}
    if isinstance(reasons, dict) and reasons:
        out.append(f"why pixels of {rec.get('scan_id')} have no point (share of the image)")
        for cam, shares in reasons.items():
            if not isinstance(shares, dict):
                continue
            top = sorted(((k, v) for k, v in shares.items() if k != "decoded" and isinstance(v, (int, float))),
                         key=lambda kv: -kv[1])
            head = f"  {cam:<8} {_pct(shares.get('decoded', 0.0))} with a point"  # a zero share is left out
            out.append((head + ("; " if top else "") + ", ".join(f"{k} {_pct(v)}" for k, v in top))[:200])
    apart = rec.get("separated") or {}
    if isinstance(apart, dict) and apart:
        out.append("lit by two copies of the pattern (a mirror), the direct copy taken apart: "
                   + ", ".join(f"{cam} {_pct(v)} of the image" for cam, v in apart.items()))
    seen = rec.get("both_seen") or {}
    if isinstance(seen, dict) and isinstance(seen.get("share"), (int, float)):
        out.append(f"camera-camera: {_pct(seen['share'])} of the {int(seen.get('pixels', 0))} pixels both cameras "
                   f"see got a point ({int(seen.get('reconstructed', 0))})")
    hdr = rec.get("hdr") or {}
    if isinstance(hdr, dict) and hdr.get("exposures_us"):
        ex = ", ".join(f"{float(e):g}" for e in hdr["exposures_us"])
        out.append(f"exposures {ex} µs; share of the decoded pixels each pass gave:")
        for cam, passes in (hdr.get("cameras") or {}).items():
            parts = [f"{float(p.get('exposure_us', 0)):g} µs {_pct(p.get('decoded_share'))}" for p in passes
                     if isinstance(p, dict)]
            out.append(f"  {cam:<8} " + ", ".join(parts))
    for w in rec.get("warnings") or []:
        out.append(f"warning   {w}"[:300])
    return out


def status_command(config: Path | None, socket: Path | None, *, as_json: bool = False) -> int:
    """Print the service's status (one screen, or JSON); exit 0 when it answered, 1 when in fault."""
    path = socket_for(config, socket)
    reply = request(path, {"cmd": "status"}, STATUS_TIMEOUT_S)
    st = reply.get("status")
    if not isinstance(st, dict) or not isinstance(st.get("state"), str):
        raise _not_the_protocol(path, reply)
    try:
        text = dumps_json(st, indent=2) if as_json else format_status(st)
    except (KeyError, TypeError, ValueError, AttributeError, IndexError, OverflowError) as exc:  # inf: int()
        raise _not_the_protocol(path, reply) from exc
    print(_shown(text))
    return 1 if st.get("state") == "fault" else 0


def _not_the_protocol(path: Path, reply: dict[str, Any]) -> ApplianceError:
    shown = repr(reply)
    shown = shown if len(shown) <= 120 else shown[:117] + "..."
    return ApplianceError(f"control socket {path}: the reply {shown} is not what scan3d's service answers; is "
                          "another program (or another version of scan3d) listening there?")


def trigger_command(config: Path | None, socket: Path | None, *, wait: bool = False) -> int:
    """Start a scan through the control socket; with ``wait``, print where its files went.

    Exit status 1 when the trigger was refused or the scan failed.
    """
    path = socket_for(config, socket)
    reply = request(path, {"cmd": "trigger", "wait": wait, "detail": "scan3d trigger"},
                    TRIGGER_WAIT_TIMEOUT_S if wait else STATUS_TIMEOUT_S)
    if not isinstance(reply.get("ok"), bool):
        raise _not_the_protocol(path, reply)
    if not reply["ok"]:
        why = ' '.join(str(reply.get('error', reply.get('result', 'refused'))).split())
        print(_shown(f"scan3d trigger: {why}"[:400]))
        return 1
    scan = reply.get("scan")
    if scan is None:
        print(_shown(f"trigger {reply.get('result')}"))
        return 0
    try:
        t = scan.get("timings_ms") or {}
        lines = [f"scan {scan['scan_id']}: {int(scan['points'])} points, {scan['location']}, "
                 f"trigger to file {_ms(t.get('trigger_to_file_ms'))} ms"]
        lines.extend(f"  {f}" for f in scan.get("files", []))
    except (KeyError, TypeError, ValueError, AttributeError, OverflowError) as exc:  # inf points: int()
        raise _not_the_protocol(path, reply) from exc
    print(_shown("\n".join(lines)))
    return 0


def tune_command(config: Path | None, socket: Path | None, *, time_budget_ms: float, apply: bool) -> int:
    """``scan3d tune`` through the running service: it probes its own rig (busy meanwhile) and prints the choice;
    with ``apply``, the service writes it into its configuration file and reloads it.

    Exit status 1 when the service refused the tune or the written file did not reload.
    """
    path = socket_for(config, socket)
    print(f"scan3d tune: through the service at {path} (it refuses triggers while it probes)", flush=True)
    reply = request(path, {"cmd": "tune", "time_budget_ms": time_budget_ms, "apply": apply}, TUNE_TIMEOUT_S)
    if not isinstance(reply.get("ok"), bool):
        raise _not_the_protocol(path, reply)
    tune = reply.get("tune")
    lines = tune.get("lines", []) if isinstance(tune, dict) else None
    if tune is not None and not (isinstance(lines, list) and all(isinstance(ln, str) for ln in lines)):
        raise _not_the_protocol(path, reply)  # the service's lines are text: anything else is another program
    if isinstance(tune, dict):
        for line in lines or []:
            print(_shown(line))
        applied = tune.get("applied")
        if isinstance(applied, dict) and applied.get("reloaded"):
            print(f"written: {applied.get('path')}: sequence.exposures_us = {applied.get('exposures_us')}; "
                  "the service reloaded it")
    if not reply["ok"]:
        print(_shown(f"scan3d tune: {' '.join(str(reply.get('error', 'refused')).split())}"[:400]))
        return 1
    return 0


def service_answers(path: Path) -> bool:
    """True when something accepts connections on the control socket ``path`` (a running service)."""
    import socket as sock

    if not Path(path).exists():
        return False
    s = sock.socket(sock.AF_UNIX, sock.SOCK_STREAM)
    s.settimeout(1.0)
    try:
        s.connect(str(path))
    except OSError:
        return False
    finally:
        s.close()
    return True
