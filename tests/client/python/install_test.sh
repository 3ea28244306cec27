#!/bin/sh
# client_python_install: the install lines of client/python/README.md, run as written (every line
# of its "install" block but the apt-get one, which scripts/deps.sh covers) in a scratch HOME with
# Debian's /usr/bin first on PATH, offline (pip --no-index). Then the installed package is imported
# from outside the source tree and makes one call. Every file the install left in the (copied)
# package directory must be one the repository's .gitignore ignores (pip's in-tree build writes
# build/ and kdrt.egg-info/ there), so running the README in a checkout leaves `git status` clean.
#   install_test.sh SOURCE_DIR WORK_DIR
set -eu
source_dir=$1
work=$2
rm -rf "$work"
mkdir -p "$work/home" "$work/checkout/client"
# A copy of the package, so pip's in-tree build leaves the source tree alone.
cp -r "$source_dir/client/python" "$work/checkout/client/python"
rm -rf "$work/checkout/client/python/build" "$work/checkout/client/python/"*.egg-info
lines=$(sed -n '/<!-- install -->/,/<!-- \/install -->/p' "$source_dir/client/python/README.md" |
        grep -v '^<!--' | grep -v '^```' | grep -v 'apt-get')
[ -n "$lines" ] || { echo "install_test.sh: no install block in client/python/README.md" >&2; exit 1; }
(cd "$work/checkout/client/python" && find . -mindepth 1 \( -type d -printf "%P/\n" -o -printf "%P\n" \) | sort) > "$work/before.txt"
cd "$work/checkout"
echo "$lines" | env -i HOME="$work/home" PATH=/usr/bin:/bin LANG=C.UTF-8 PIP_NO_INDEX=1 sh -eux
(cd "$work/checkout/client/python" && find . -mindepth 1 \( -type d -printf "%P/\n" -o -printf "%P\n" \) | sort) > "$work/after.txt"
left=$(comm -13 "$work/before.txt" "$work/after.txt" | sed 's|^|client/python/|')
if [ -n "$left" ] && command -v git >/dev/null && git -C "$source_dir" rev-parse 2>/dev/null; then
    not_ignored=$(echo "$left" | while read -r path; do
        git -C "$source_dir" check-ignore -q --no-index "$path" || echo "$path"
    done)
    if [ -n "$not_ignored" ]; then
        echo "install_test.sh: the install left files that .gitignore does not ignore:" >&2
        echo "$not_ignored" >&2
        exit 1
    fi
fi
venv_python="$work/home/.venvs/kdrt/bin/python"
cd "$work"
env -i HOME="$work/home" PATH=/usr/bin:/bin "$venv_python" - "$work/home" <<'PY'
import sys
import kdrt, numpy
home = sys.argv[1]
assert kdrt.__file__.startswith(home), kdrt.__file__   # the installed copy, not the source
try:
    kdrt.Client("http://127.0.0.1:9", max_retries=0).health()
except kdrt.Error as e:
    assert e.kind == "connection", e
else:
    raise AssertionError("a call to a closed port succeeded")
print("installed kdrt", kdrt.__version__, "with numpy", numpy.__version__, "at", kdrt.__file__)
PY
