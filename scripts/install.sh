#!/usr/bin/env bash
# Install compd as a service: a venv under $PREFIX, /usr/bin/compd, the systemd units, a
# config under /etc/compd, the compd user. `make install` runs it; DESTDIR stages into a
# folder instead (packaging: scripts/build_deb.sh, tests): then no user is created, systemd
# is not told, and the staged files name only their final paths (copy the tree to / to use it).
#
#   sudo make install                      # or: sudo scripts/install.sh
#   DESTDIR=/tmp/stage scripts/install.sh  # stage only
#
# Variables: PREFIX (/opt/compd), BINDIR (/usr/bin: the compd symlink), SYSCONFDIR (/etc),
# UNITDIR (/etc/systemd/system), SYSUSERSDIR (/usr/lib/sysusers.d), PYTHON (python3, 3.11+
# with the venv module), EXTRAS (every extra in pyproject.toml but `test`, comma-separated),
# PIP_ARGS (extra pip options, e.g. --no-index --find-links DIR; --no-deps when the
# dependencies come some other way).
#
# A staged venv holds no byte code (.pyc files name the path they were compiled at): the
# installer compiles it in place, e.g. `$PREFIX/venv/bin/python -m compileall -q $PREFIX/venv`
# (the Debian package's postinst does).
set -euo pipefail
# the venv, units and config must be readable by the user compd, whatever root's umask is
umask 022

DESTDIR=${DESTDIR:-}
PREFIX=${PREFIX:-/opt/compd}
BINDIR=${BINDIR:-/usr/bin}
SYSCONFDIR=${SYSCONFDIR:-/etc}
UNITDIR=${UNITDIR:-/etc/systemd/system}
SYSUSERSDIR=${SYSUSERSDIR:-/usr/lib/sysusers.d}
PYTHON=${PYTHON:-python3}
PIP_ARGS=${PIP_ARGS:-}
SRC=$(cd "$(dirname "${BASH_SOURCE[0]}")/.." && pwd)

say() { echo "install: $*"; }
die() { echo "install: $*" >&2; exit 1; }
# an outer PYTHONPATH (a checkout) would make pip think compd is already installed
unset PYTHONPATH

command -v "$PYTHON" >/dev/null || die "no Python interpreter $PYTHON (set PYTHON=...)"
# a venv's python (make install passes the checkout's .venv) stands for its base interpreter, which
# makes the new venv: pyvenv.cfg would name the checkout otherwise
PYTHON=$("$PYTHON" -c 'import sys; print(getattr(sys, "_base_executable", "") or sys.executable)')
# the runtime extras: every optional dependency group but the test tools
if [ -z "${EXTRAS+set}" ]; then
    EXTRAS=$("$PYTHON" -c 'import sys, tomllib
extras = tomllib.load(open(sys.argv[1], "rb"))["project"]["optional-dependencies"]
print(",".join(e for e in extras if e != "test"))' "$SRC/pyproject.toml") || die "cannot read the extras from $SRC/pyproject.toml"
fi
if [ -n "$DESTDIR" ]; then
    mkdir -p "$DESTDIR"
    DESTDIR=$(cd "$DESTDIR" && pwd)
fi

venv="$DESTDIR$PREFIX/venv"
work=$(mktemp -d)
running=""  # the compd units that run now (an upgrade over them: said at the end)
trap 'rm -rf "$work"' EXIT

say "venv $venv (extras: ${EXTRAS:-none})"
mkdir -p "$(dirname "$venv")"
# a normal venv with pip in it, so the plant's engineer can inspect it (pip list, pip check); a newer compd
# or another extra comes from running this again from the source tree (or a newer package), never pip by hand
[ -x "$venv/bin/python" ] || "$PYTHON" -m venv "$venv" || die "$PYTHON -m venv failed (Debian: apt install python3-venv)"
# a venv from an older install.sh has no pip: give it one
"$venv/bin/python" -m pip --version >/dev/null 2>&1 || "$venv/bin/python" -m ensurepip -q

say "building the compd wheel"
# build from a copy so the checkout gets no build/ or egg-info litter
mkdir "$work/src"
tar -C "$SRC" --exclude=./.venv --exclude=./.git --exclude='*.egg-info' --exclude=./build -cf - . | tar -C "$work/src" -xf -
"$venv/bin/python" -m pip wheel -q --disable-pip-version-check --no-deps -w "$work" "$work/src" 2>"$work/build.log" ||
    { cat "$work/build.log" >&2; exit 1; }
wheel=$(ls "$work"/compd-*.whl)
# staged, pip writes no byte code: relocate.py would remove it (it names the stage), so compiling it is waste
nocompile=""
[ -z "$DESTDIR" ] || nocompile=--no-compile
# shellcheck disable=SC2086
"$venv/bin/python" -m pip install -q --upgrade --disable-pip-version-check --no-warn-script-location $nocompile \
    $PIP_ARGS "$wheel${EXTRAS:+[$EXTRAS]}"

say "$BINDIR/compd -> $PREFIX/venv/bin/compd"
install -d "$DESTDIR$BINDIR"
ln -sfn "$PREFIX/venv/bin/compd" "$DESTDIR$BINDIR/compd"

say "docs, units and the drop-in examples (real-time, network)"
install -d "$DESTDIR$PREFIX/docs" "$DESTDIR$PREFIX/systemd" "$DESTDIR$UNITDIR" "$DESTDIR$SYSUSERSDIR"
install -m 0644 "$SRC"/docs/*.md "$DESTDIR$PREFIX/docs/"
for unit in compd.service compd@.service; do
    sed "s#/opt/compd#$PREFIX#g; s#/etc/compd#$SYSCONFDIR/compd#g" "$SRC/systemd/$unit" >"$work/$unit"
    install -m 0644 "$work/$unit" "$DESTDIR$UNITDIR/$unit"
done
for dropin in realtime.conf.example network.conf.example; do
    install -m 0644 "$SRC/systemd/$dropin" "$DESTDIR$PREFIX/systemd/"
done
install -m 0644 "$SRC/systemd/compd.sysusers" "$DESTDIR$SYSUSERSDIR/compd.conf"

install -d -m 0755 "$DESTDIR$SYSCONFDIR/compd"
if [ -e "$DESTDIR$SYSCONFDIR/compd/compd.yaml" ]; then
    say "keeping the existing $SYSCONFDIR/compd/compd.yaml"
else
    install -m 0644 "$SRC/configs/service.yaml" "$DESTDIR$SYSCONFDIR/compd/compd.yaml"
    say "config $SYSCONFDIR/compd/compd.yaml (observe mode on the simulator: edit it, see docs)"
fi

if [ -n "$DESTDIR" ]; then
    say "relocating the staged venv to $PREFIX/venv"
    "$PYTHON" "$SRC/packaging/relocate.py" --destdir "$DESTDIR" --venv "$PREFIX/venv" --forbid "$work"
else
    if ! id compd >/dev/null 2>&1; then
        if command -v systemd-sysusers >/dev/null; then
            systemd-sysusers "$SYSUSERSDIR/compd.conf"
        else
            useradd --system --home-dir /var/lib/compd --shell /usr/sbin/nologin --user-group compd
            usermod -a -G dialout compd
        fi
        say "user compd created"
    fi
    if [ -d /run/systemd/system ]; then
        systemctl daemon-reload
        # a compd that runs keeps the old code it has loaded (and would load the rest from these files)
        running=$(systemctl list-units --type=service --state=active --no-legend --plain \
            'compd.service' 'compd@*.service' 2>/dev/null | awk '{ printf "%s ", $1 }') || running=""
    fi
fi
if [ -n "$DESTDIR" ]; then
    say "done: staged in $DESTDIR (its files name their final paths: copy the tree to /, or package it)"
elif [ -n "$running" ]; then
    say "done. Still running the old version: ${running% }; restart it to run this one: systemctl restart ${running% }"
    say "(not reload: a reload rereads the config, the running daemon keeps the old code it has loaded)"
else
    say "done. Next: edit $SYSCONFDIR/compd/compd.yaml, then: systemctl enable --now compd"
fi
