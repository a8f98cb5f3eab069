# Writes compd(1) for the Debian package from `compd --help` (scripts/build_deb.sh runs it).
"""compd.1 from the top-level help: the commands as `compd --help` lists them, the files the
package installs, and where the documentation is.

    compd --help | python packaging/deb/manpage.py --version 0.1.0 --date 2026-01-01 > compd.1
"""

from __future__ import annotations

import argparse
import re
import sys


def roff(text: str) -> str:
    """Text safe for a roff line: backslashes and hyphens escaped, no line led by a control character."""
    text = text.replace("\\", "\\e").replace("-", "\\-")
    return "\\&" + text if text[:1] in {".", "'"} else text


def commands(help_text: str) -> list[tuple[str, str]]:
    """(name, summary) of each command in argparse's listing (a long name puts its summary on the next lines)."""
    out: list[tuple[str, str]] = []
    lines = help_text.splitlines()
    try:
        start = next(i for i, line in enumerate(lines) if line.strip() == "COMMAND") + 1
    except StopIteration:
        return out
    for line in lines[start:]:
        if not line.strip():
            break
        m = re.match(r"^ {4}(\S+)(?:\s{2,}(.*))?$", line)
        if m:
            out.append((m.group(1), (m.group(2) or "").strip()))
        elif out:
            name, summary = out[-1]
            out[-1] = (name, f"{summary} {line.strip()}".strip())
    return out


def render(help_text: str, version: str, date: str) -> str:
    lines = help_text.splitlines()
    description = next((line.strip() for line in lines[1:] if line.strip()), "thermal-error compensation")
    out = [
        f'.TH COMPD 1 "{date}" "compd {roff(version)}" "User Commands"',
        ".SH NAME",
        "compd \\- " + roff(description[:1].lower() + description[1:].rstrip(".")),
        ".SH SYNOPSIS",
        ".B compd",
        "[\\fB\\-\\-version\\fR] \\fICOMMAND\\fR [\\fIARGS\\fR]",
        ".SH DESCRIPTION",
        roff(description),
        "Every command's arguments: \\fBcompd\\fR \\fICOMMAND\\fR \\fB\\-\\-help\\fR.",
        ".SH COMMANDS",
    ]
    for name, summary in commands(help_text):
        out += [".TP", f"\\fB{roff(name)}\\fR", roff(summary)]
    out += [
        ".SH FILES",
        ".TP",
        "\\fI/etc/compd/compd.yaml\\fR",
        "the config compd.service runs (compd@NAME.service runs /etc/compd/NAME.yaml)",
        ".TP",
        "\\fI/opt/compd/venv\\fR",
        "compd and its Python dependencies (a venv: its pip is for inspection; a newer compd comes as a newer"
        " package, never through pip). The package compd holds the daemon and what it needs; compd\\-commissioning"
        " adds the fits, plots, reports, the simulator and the OPC UA server's stack: without it those commands say"
        " so",
        ".TP",
        "\\fI/opt/compd/docs\\fR",
        "the documentation: commissioning.md, configuration.md, troubleshooting.md and the rest",
        ".TP",
        "\\fI/opt/compd/systemd\\fR",
        "opt\\-in drop\\-ins for the units: real\\-time scheduling and the device network",
        ".SH UPGRADES",
        "After installing a newer package, restart every running compd: \\fBsystemctl restart compd\\fR (and each"
        " \\fBcompd@\\fR\\fINAME\\fR). A reload is not enough: it rereads the config, while the running daemon keeps"
        " the code it has loaded and would load the rest from the new files. The package never restarts compd"
        " itself (a restart takes the correction to the safe state); its postinst names what runs.",
        ".SH SEE ALSO",
        "\\fBsystemctl\\fR(1), \\fBjournalctl\\fR(1), /opt/compd/docs/commissioning.md",
    ]
    return "\n".join(out) + "\n"


def main(argv: list[str] | None = None) -> int:
    ap = argparse.ArgumentParser(description="Write compd(1) from `compd --help` on stdin.")
    ap.add_argument("--version", required=True, help="the package's version")
    ap.add_argument("--date", required=True, help="the page's date, e.g. 2026-01-01")
    args = ap.parse_args(argv)
    help_text = sys.stdin.read()
    if not commands(help_text):
        print("manpage: stdin holds no command listing (expected `compd --help`)", file=sys.stderr)
        return 2
    sys.stdout.write(render(help_text, args.version, args.date))
    return 0


if __name__ == "__main__":
    sys.exit(main())
