#!/usr/bin/env bash
# The oldest Python 3.12 or later this machine has (the widest choice of wheels), for PyPI's
# dolfinx wheel (cp312, abi3): its path on stdout, or nothing. Looked for on the PATH, then
# among pyenv's versions (Debian 12's own python3 is 3.11).
ok() { "$1" -c 'import sys, venv; sys.exit(sys.version_info < (3, 12))' >/dev/null 2>&1; }
for p in python3.12 python3.13 python3.14 python3; do
  exe=$(command -v "$p") && ok "$exe" && { echo "$exe"; exit 0; }
done
root=$(pyenv root 2>/dev/null || echo "$HOME/.pyenv")
for exe in $(ls -d "$root"/versions/3.*/bin/python3 2>/dev/null | sort -V); do
  ok "$exe" && { echo "$exe"; exit 0; }
done
exit 0
