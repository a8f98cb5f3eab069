#!/usr/bin/env bash
# Build compd's Debian packages (make deb): stage with scripts/install.sh, split, add DEBIAN/ and the docs, dpkg-deb.
#
#   scripts/build_deb.sh [--out DIR]     # writes DIR/compd_<version>-<revision>_<arch>.deb and
#                                        # DIR/compd-commissioning_<version>-<revision>_<arch>.deb (DIR: build/)
#
# Together the two install what `make install` does, at PREFIX=/opt/compd: a venv with every
# runtime extra, /usr/bin/compd, the units in /lib/systemd/system, /etc/compd/compd.yaml (a
# conffile), the sysusers file. packaging/deb/split.py's table decides which files go into
# compd-commissioning (the fits, plots, reports, the simulator and the rig, scipy, matplotlib,
# the OPC UA stack); the rest is the daemon package compd, with the units, the config, the
# user and every maintainer script of its own (packaging/deb/; the other's are
# packaging/deb/commissioning.*). compd-commissioning depends on compd of the same version.
# It stages in DIR/deb/root and DIR/deb/commissioning and removes them after (KEEP_STAGE=1 keeps them).
#
# The build is reproducible: SOURCE_DATE_EPOCH (else the last commit's date) dates the changelog
# and the man page, every file's time is clamped to it, Installed-Size is counted as
# dpkg-gencontrol does (file sizes, not the disk's blocks): the same commit builds the same bytes
# (`make deb-twice` checks it).
#
# Variables: PYTHON (/usr/bin/python3: a Debian interpreter, which the package depends on),
# DEB_REVISION (1: the Debian revision after the version in pyproject.toml), DEB_MAINTAINER,
# DEB_COMPRESS (xz, or gzip; bookworm's lintian calls a zstd member malformed),
# DEB_COMPRESS_LEVEL (dpkg-deb's default, 6; 1 builds in a tenth of the time, 20 % larger),
# PIP_ARGS (for install.sh), KEEP_STAGE.
set -euo pipefail
umask 022

SRC=$(cd "$(dirname "${BASH_SOURCE[0]}")/.." && pwd)
PKG="$SRC/packaging/deb"
PYTHON=${PYTHON:-/usr/bin/python3}
DEB_REVISION=${DEB_REVISION:-1}
DEB_MAINTAINER=${DEB_MAINTAINER:-compd maintainers <compd-maintainers@example.com>}
DEB_COMPRESS=${DEB_COMPRESS:-xz}
DEB_COMPRESS_LEVEL=${DEB_COMPRESS_LEVEL:-}
PREFIX=/opt/compd
UNITDIR=/lib/systemd/system

die() { echo "build_deb: $*" >&2; exit 1; }
say() { echo "build_deb: $*"; }

out="$SRC/build"
while [ $# -gt 0 ]; do
    case "$1" in
    --out) [ $# -ge 2 ] || die "--out needs a folder"; out=$2; shift 2 ;;
    --out=*) out=${1#--out=}; shift ;;
    -h | --help) awk 'NR > 1 && /^#/ { sub(/^# ?/, ""); print; next } NR > 1 { exit }' "${BASH_SOURCE[0]}"; exit 0 ;;
    *) die "unknown argument '$1' (usage: scripts/build_deb.sh [--out DIR])" ;;
    esac
done

for tool in dpkg-deb dpkg-shlibdeps; do
    command -v "$tool" >/dev/null || die "needs $tool (apt install dpkg-dev)"
done
command -v "$PYTHON" >/dev/null || die "no Python interpreter $PYTHON (set PYTHON=/usr/bin/python3)"
# the venv links to this interpreter: the package depends on the Debian package that ships it
python=$(readlink -f "$(command -v "$PYTHON")")
pypkg=$(dpkg -S "$python" 2>/dev/null | head -n1 | cut -d: -f1) || true
[ -n "$pypkg" ] || die "$python belongs to no Debian package, so the package could not depend on it (set PYTHON=/usr/bin/python3)"
# Debian ships the interpreter in pythonX.Y-minimal; pythonX.Y adds the standard library the venv needs
pypkg=${pypkg%-minimal}
dpkg-query -W -f='${Status}' "$pypkg" 2>/dev/null | grep -q 'ok installed' || die "$pypkg is not installed (apt install $pypkg)"
"$python" -c 'import sys; sys.exit(sys.version_info < (3, 11))' || die "$python is older than Python 3.11"
"$python" -c 'import ensurepip, venv' 2>/dev/null || die "$python has no venv module (apt install python3-venv)"

upstream=$("$python" -c 'import sys, tomllib; print(tomllib.load(open(sys.argv[1], "rb"))["project"]["version"])' "$SRC/pyproject.toml")
# PEP 440 to Debian: pre-releases and dev releases sort before the release (~), post releases after (+)
debupstream=$("$python" -c 'import re, sys; v = sys.argv[1]
v = re.sub(r"[.-]?(a|b|rc|dev)(\d*)", r"~\1\2", v); print(re.sub(r"[.-]?post(\d*)", r"+post\1", v))' "$upstream")
version="$debupstream-$DEB_REVISION"
arch=$(dpkg --print-architecture)

mkdir -p "$out"
out=$(cd "$out" && pwd)
work="$out/deb"
root="$work/root"
croot="$work/commissioning"
deb="$out/compd_${version}_${arch}.deb"
cdeb="$out/compd-commissioning_${version}_${arch}.deb"
rm -rf "$work"
mkdir -p "$work"
# dates: SOURCE_DATE_EPOCH, else the last commit's (the same package from the same commit), else now
epoch=${SOURCE_DATE_EPOCH:-$(git -C "$SRC" log -1 --format=%ct 2>/dev/null || date +%s)}
export SOURCE_DATE_EPOCH=$epoch

say "compd $version ($arch) on $python ($pypkg), staged in $root"
DESTDIR="$root" PREFIX="$PREFIX" BINDIR=/usr/bin SYSCONFDIR=/etc UNITDIR="$UNITDIR" \
    SYSUSERSDIR=/usr/lib/sysusers.d PYTHON="$python" PIP_ARGS="${PIP_ARGS:-}" \
    bash "$SRC/scripts/install.sh" | sed 's/^/  /'
venv="$root$PREFIX/venv"

# modes as Debian's tools expect them: shared libraries are not executable, and in the venv's
# lib/ only ELF files and scripts run by the venv's own python keep an x bit (the rest are
# modules and data that some wheels ship executable, or with a #! naming another python)
find "$root$PREFIX" -type f \( -name '*.so' -o -name '*.so.*' \) -perm /111 -exec chmod a-x {} +
while IFS= read -r -d '' file; do
    head=$(head -c 64 "$file" | tr -d '\0' | head -n1)
    case "$head" in
    $'\x7f'ELF* | "#!$PREFIX/venv/bin/python"*) ;;
    *) chmod a-x "$file" ;;
    esac
done < <(find "$venv/lib" -type f -perm /111 -print0)

site=$(cd "$venv/lib" && echo python3*/site-packages)
# the staged compd's own --help, before the split takes anything (byte code not written: the stage must hold none)
PYTHONDONTWRITEBYTECODE=1 "$venv/bin/python" -m compd --help >"$work/help.txt"

say "split: compd-commissioning's files (packaging/deb/split.py) to $croot"
"$python" "$PKG/split.py" --site "$venv/lib/$site" --root "$root" --to "$croot" | sed 's/^/  /'

say "docs: copyright, changelog.Debian.gz, compd(1), lintian overrides"
first=$(git -C "$SRC" log --reverse --format=%ct 2>/dev/null | head -n1) || true
years=$(date -u -d "@${first:-$epoch}" +%Y)
[ "$(date -u -d "@$epoch" +%Y)" = "$years" ] || years="$years-$(date -u -d "@$epoch" +%Y)"
for package in compd compd-commissioning; do
    tree=$root
    [ "$package" = compd ] || tree=$croot
    doc="$tree/usr/share/doc/$package"
    install -d "$doc" "$tree/usr/share/lintian/overrides"
    "$python" "$PKG/copyright.py" --package "$package" --site-packages "$tree$PREFIX/venv/lib/$site" \
        --final-site "$PREFIX/venv/lib/$site" --years "$years" >"$doc/copyright"
    sed "s|@VERSION@|$version|g; s|@UPSTREAM@|$upstream|g; s|@MAINTAINER@|$DEB_MAINTAINER|g; s|@DATE@|$(LC_ALL=C date -u -R -d "@$epoch")|g" \
        "$PKG/changelog.in" | gzip -9n >"$doc/changelog.Debian.gz"
done
install -m 0644 "$PKG/lintian-overrides" "$root/usr/share/lintian/overrides/compd"
install -m 0644 "$PKG/commissioning.lintian-overrides" "$croot/usr/share/lintian/overrides/compd-commissioning"
install -d "$root/usr/share/man/man1"
"$python" "$PKG/manpage.py" --version "$version" --date "$(date -u -d "@$epoch" +%Y-%m-%d)" <"$work/help.txt" |
    gzip -9n >"$root/usr/share/man/man1/compd.1.gz"

# installed_size TREE: KiB as dpkg-gencontrol counts them (each file's size rounded up, 1 for each
# folder), so the figure does not hang on the file system the stage is on
installed_size() {
    find "$1" -path "$1/DEBIAN" -prune -o -printf '%y %s\n' |
        awk '$1 == "f" || $1 == "l" { kib += int(($2 + 1023) / 1024); next } { kib += 1 } END { print kib }'
}
# shlibdeps TREE NAME: the shared libraries the wheels' binaries in TREE need from the system (each
# wheel's *.libs it brings; those of the other package's wheels are not looked for)
shlibdeps() {
    local tree=$1 name=$2 elves libdirs out
    mkdir -p "$work/shlibs-$name/debian"
    printf 'Source: compd\n\nPackage: %s\nArchitecture: any\n' "$name" >"$work/shlibs-$name/debian/control"
    mapfile -t elves < <(find "$tree$PREFIX" -type f \( -name '*.so' -o -name '*.so.*' \) | LC_ALL=C sort)
    mapfile -t libdirs < <(find "$root$PREFIX" "$croot$PREFIX" -type d -name '*.libs' | LC_ALL=C sort)
    [ "${#elves[@]}" -gt 0 ] || return 0
    out=$(cd "$work/shlibs-$name" && dpkg-shlibdeps -O --ignore-missing-info "${libdirs[@]/#/-l}" "${elves[@]/#/-e}" 2>"$work/shlibdeps.log") ||
        { cat "$work/shlibdeps.log" >&2; die "dpkg-shlibdeps failed for $name"; }
    echo "${out#shlibs:Depends=}"
}

say "DEBIAN: control, conffiles, md5sums, maintainer scripts"
install -d -m 0755 "$root/DEBIAN" "$croot/DEBIAN"
for script in postinst prerm postrm; do
    install -m 0755 "$PKG/$script" "$root/DEBIAN/$script"
done
for script in postinst prerm; do
    install -m 0755 "$PKG/commissioning.$script" "$croot/DEBIAN/$script"
done
(cd "$root" && find etc -type f | LC_ALL=C sort | sed 's|^|/|') >"$root/DEBIAN/conffiles"
shlibs=$(shlibdeps "$root" compd)
# adduser: the postinst's way to create the user where systemd-sysusers is missing
depends="$pypkg, adduser${shlibs:+, $shlibs}"
sed "s|@VERSION@|$version|; s|@ARCH@|$arch|; s|@MAINTAINER@|$DEB_MAINTAINER|; s|@INSTALLED_SIZE@|$(installed_size "$root")|; s|@DEPENDS@|$depends|" \
    "$PKG/control.in" >"$root/DEBIAN/control"
shlibs=$(shlibdeps "$croot" compd-commissioning)
depends="compd (= $version)${shlibs:+, $shlibs}"
sed "s|@VERSION@|$version|; s|@ARCH@|$arch|; s|@MAINTAINER@|$DEB_MAINTAINER|; s|@INSTALLED_SIZE@|$(installed_size "$croot")|; s|@DEPENDS@|$depends|" \
    "$PKG/commissioning.control.in" >"$croot/DEBIAN/control"
for tree in "$root" "$croot"; do
    (cd "$tree" && find . -path ./DEBIAN -prune -o -type f -printf '%P\0' | LC_ALL=C sort -z | xargs -0 md5sum) >"$tree/DEBIAN/md5sums"
    # every time no later than the source's: the same commit, the same archive
    find "$tree" -newermt "@$epoch" -exec touch --no-dereference --date="@$epoch" {} +
done
# nothing in either package may name the stage or the build folder
"$python" "$SRC/packaging/relocate.py" --check-only --destdir "$root" --venv "$PREFIX/venv" --forbid "$work" --also "$croot"

say "dpkg-deb ($DEB_COMPRESS${DEB_COMPRESS_LEVEL:+ -z$DEB_COMPRESS_LEVEL})"
for pair in "$root:$deb" "$croot:$cdeb"; do
    # SOURCE_DATE_EPOCH (exported) dates the ar members and clamps the tar entries' times
    dpkg-deb --root-owner-group -Z"$DEB_COMPRESS" ${DEB_COMPRESS_LEVEL:+-z"$DEB_COMPRESS_LEVEL"} --build "${pair%%:*}" "${pair#*:}" >/dev/null
done
[ -n "${KEEP_STAGE:-}" ] || rm -rf "$work"
say "$deb ($(du -h "$deb" | cut -f1))"
say "$cdeb ($(du -h "$cdeb" | cut -f1))"
