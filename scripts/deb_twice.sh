#!/usr/bin/env bash
# Build compd's Debian packages twice, in two folders, and compare them byte for byte (make deb-twice; make accept).
#
#   scripts/deb_twice.sh [--out DIR]     # DIR/a and DIR/b (DIR: build/deb-twice); exit 1 when a package differs
#
# The same commit must give the same packages (scripts/build_deb.sh: SOURCE_DATE_EPOCH from the last
# commit, every time clamped to it, Installed-Size from file sizes); the second build runs in another
# folder, so a build path that leaks into a package shows too. Variables: those of build_deb.sh.
set -euo pipefail

SRC=$(cd "$(dirname "${BASH_SOURCE[0]}")/.." && pwd)
out="$SRC/build/deb-twice"
case "${1:-}" in
--out) out=$2 ;;
--out=*) out=${1#--out=} ;;
"") ;;
*) echo "deb_twice: unknown argument '$1' (usage: scripts/deb_twice.sh [--out DIR])" >&2; exit 2 ;;
esac

rm -rf "$out"
mkdir -p "$out"
for run in a b; do
    "$SRC/scripts/build_deb.sh" --out "$out/$run" >"$out/$run.log" 2>&1 ||
        { tail -n 20 "$out/$run.log" >&2; echo "deb_twice: build $run failed (log: $out/$run.log)" >&2; exit 1; }
done
status=0
for deb in "$out"/a/*.deb; do
    name=$(basename "$deb")
    one=$(sha256sum <"$deb" | cut -d' ' -f1)
    two=$(sha256sum <"$out/b/$name" 2>/dev/null | cut -d' ' -f1) || two="(missing)"
    if [ "$one" = "$two" ]; then
        echo "deb_twice: $name: the same bytes twice, sha256 $one"
    else
        echo "deb_twice: $name differs between the builds: $one and $two (diffoscope $deb $out/b/$name)" >&2
        status=1
    fi
done
exit $status
