#!/usr/bin/env bash
# Installs what a fresh Debian machine lacks to build and test b2dr: the Vulkan loader, lavapipe (CPU Vulkan)
# when no Vulkan driver is installed, and the Khronos validation layer. Needs root for apt-get; without root it
# only reports what is missing. Sourced by tools/test.sh and tools/run.sh.
set -euo pipefail

missing=()
ldconfig -p 2>/dev/null | grep -q 'libvulkan.so.1' || missing+=(libvulkan1)
# a Vulkan driver (ICD manifest) in either standard place; lavapipe when there is none
find /usr/share/vulkan/icd.d /etc/vulkan/icd.d -name '*.json' 2>/dev/null | grep -q . || missing+=(mesa-vulkan-drivers)
ls /usr/share/vulkan/explicit_layer.d/VkLayer_khronos_validation.json >/dev/null 2>&1 || missing+=(vulkan-validationlayers)
command -v vulkaninfo >/dev/null 2>&1 || missing+=(vulkan-tools)
# python3 with its venv module: the planner's virtualenv of tools/run.sh (tools/ensure-planner-venv.sh) and the
# tests' (tools/ensure-python.sh)
python3 -c "import venv, ensurepip" >/dev/null 2>&1 || missing+=(python3-venv)

if [ ${#missing[@]} -gt 0 ]; then
  if [ "$(id -u)" = 0 ] && command -v apt-get >/dev/null 2>&1; then
    echo "b2dr: installing ${missing[*]}" >&2
    export DEBIAN_FRONTEND=noninteractive
    apt-get update -qq
    apt-get install -y -qq "${missing[@]}" >/dev/null
  else
    echo "b2dr: missing ${missing[*]} (install them with apt-get as root); Vulkan tests will skip" >&2
  fi
fi

if ! command -v cargo >/dev/null 2>&1; then
  [ -f "$HOME/.cargo/env" ] && . "$HOME/.cargo/env"
fi
command -v cargo >/dev/null 2>&1 || { echo "b2dr: cargo not found: install Rust >= 1.85 (https://rustup.rs)" >&2; exit 1; }
