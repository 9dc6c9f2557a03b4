#!/usr/bin/env bash
# Dr.Jit 1.5's LLVM backend needs libLLVM >= 16 (Debian's libLLVM 15 fails
# with "Cannot select ... fminimum"). Install Debian's libllvm19 when no
# suitable libLLVM is present. Idempotent: does nothing when one is found.
set -euo pipefail
found=""
for d in /usr/lib/x86_64-linux-gnu /usr/lib/aarch64-linux-gnu /usr/lib /usr/local/lib /usr/lib64; do
  for f in "$d"/libLLVM-[0-9]*.so* "$d"/libLLVM.so.[0-9]*; do
    [ -e "$f" ] || continue
    v=$(basename "$f" | sed -E 's/^libLLVM[-.](so\.)?([0-9]+).*/\2/')
    if [[ "$v" =~ ^[0-9]+$ ]] && [ "$v" -ge 16 ]; then found="$f"; break 2; fi
  done
done
if [ -n "${DRJIT_LIBLLVM_PATH:-}" ] && [ -e "${DRJIT_LIBLLVM_PATH}" ]; then found="$DRJIT_LIBLLVM_PATH"; fi
if [ -n "$found" ]; then
  echo "libLLVM >= 16 found: $found"
  exit 0
fi
echo "No libLLVM >= 16 found: installing Debian's libllvm19"
SUDO=""
if [ "$(id -u)" -ne 0 ]; then SUDO="sudo"; fi
if ! command -v apt-get >/dev/null 2>&1; then
  echo "error: apt-get not available; install libLLVM >= 16 and set DRJIT_LIBLLVM_PATH" >&2
  exit 2
fi
$SUDO apt-get update -qq
DEBIAN_FRONTEND=noninteractive $SUDO apt-get install -y -qq libllvm19
