#!/usr/bin/env bash
# Install compd as a service: a venv under $PREFIX, the systemd units, a config under
# /etc/compd, the compd user. `make install` runs it; DESTDIR stages into a folder instead
# (packaging, tests): then no user is created and systemd is not told.
#
#   sudo make install                      # or: sudo scripts/install.sh
#   DESTDIR=/tmp/stage scripts/install.sh  # stage only
#
# Variables: PREFIX (/opt/compd), SYSCONFDIR (/etc), UNITDIR (/etc/systemd/system),
# SYSUSERSDIR (/usr/lib/sysusers.d), PYTHON (python3, must have pip >= 22.3),
# EXTRAS (metrics), PIP_ARGS (extra pip options, e.g. --no-index --find-links DIR;
# --no-deps when the dependencies come some other way).
set -euo pipefail

DESTDIR=${DESTDIR:-}
PREFIX=${PREFIX:-/opt/compd}
SYSCONFDIR=${SYSCONFDIR:-/etc}
UNITDIR=${UNITDIR:-/etc/systemd/system}
SYSUSERSDIR=${SYSUSERSDIR:-/usr/lib/sysusers.d}
PYTHON=${PYTHON:-python3}
EXTRAS=${EXTRAS:-metrics}
PIP_ARGS=${PIP_ARGS:-}
SRC=$(cd "$(dirname "${BASH_SOURCE[0]}")/.." && pwd)

say() { echo "install: $*"; }
# an outer PYTHONPATH (a checkout) would make pip think compd is already installed
unset PYTHONPATH

venv="$DESTDIR$PREFIX/venv"
work=$(mktemp -d)
trap 'rm -rf "$work"' EXIT

say "building the compd wheel"
# build from a copy so the checkout gets no build/ or egg-info litter
mkdir "$work/src"
tar -C "$SRC" --exclude=./.venv --exclude=./.git --exclude='*.egg-info' --exclude=./build -cf - . | tar -C "$work/src" -xf -
"$PYTHON" -m pip wheel -q --no-deps -w "$work" "$work/src" 2>"$work/build.log" || { cat "$work/build.log" >&2; exit 1; }
wheel=$(ls "$work"/compd-*.whl)

say "venv $venv"
mkdir -p "$(dirname "$venv")"
[ -x "$venv/bin/python" ] || "$PYTHON" -m venv --without-pip "$venv"
# shellcheck disable=SC2086
"$PYTHON" -m pip --python "$venv/bin/python" install -q --upgrade $PIP_ARGS "$wheel${EXTRAS:+[$EXTRAS]}"

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

if [ -z "$DESTDIR" ]; then
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
    fi
fi
say "done. Next: edit $SYSCONFDIR/compd/compd.yaml, then: systemctl enable --now compd"
