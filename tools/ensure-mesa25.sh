#!/usr/bin/env bash
# A second Vulkan driver for the tests: Mesa 25 lavapipe (llvmpipe) from Debian bookworm-backports, unpacked
# into a cache folder beside the system driver: no system-wide upgrade, nothing installed with dpkg, no root
# needed. Sourced by tools/test.sh, or run directly (it then prints the variables). Sets
#   B2DR_MESA25_ICD   the ICD manifest (JSON) whose library_path is the unpacked libvulkan_lvp.so
#   B2DR_MESA25_LIBS  the unpacked library folder: the LD_LIBRARY_PATH entry for newer libraries the driver needs
#                     than the system has (libdrm2 from backports); set it only for the Mesa 25 run
#   B2DR_MESA25_VERSION  the Debian version unpacked, e.g. 25.0.7-2~bpo12+1
# A run selects the driver with VK_ICD_FILENAMES=$B2DR_MESA25_ICD (and VK_DRIVER_FILES, its newer name).
#
# Cache: ${B2DR_MESA25_DIR:-~/.cache/b2dr-mesa25}; a second call finds it complete and only sets the variables.
# Download: apt-get with a private configuration (its own sources list with bookworm and bookworm-backports, its
# own package lists and archive cache under the cache folder): `apt-get update` there, `apt-get download` of
# mesa-vulkan-drivers from bookworm-backports and of every dependency the system lacks or has too old a version
# of (libdrm2 >= 2.4.121 on bookworm; libLLVM-15 is bookworm's), `dpkg-deb -x` of each. Needs apt-get and
# dpkg-deb (Debian or a derivative, amd64 or arm64) and deb.debian.org the first time; afterwards it works
# offline. If the download fails it says so and returns non-zero: tools/test.sh then fails the run (CI must not
# pass without the second driver); B2DR_MESA25=0 skips the Mesa 25 pass on purpose (printed in the log).
# B2DR_MESA25_PIN=<version> downloads that exact version of mesa-vulkan-drivers instead of backports' newest.
set -euo pipefail

b2dr_mesa25() {
  local dir="${B2DR_MESA25_DIR:-$HOME/.cache/b2dr-mesa25}"
  local suite=bookworm-backports
  local stamp="$dir/complete"
  if [ ! -f "$stamp" ]; then
    local tool
    for tool in apt-get apt-cache dpkg-deb dpkg-query; do
      command -v "$tool" >/dev/null 2>&1 || {
        echo "b2dr: Mesa 25 driver: $tool not found (tools/ensure-mesa25.sh needs a Debian system)" >&2
        return 1
      }
    done
    echo "b2dr: fetching Mesa 25 lavapipe from $suite into $dir (once)" >&2
    rm -rf "$dir/root" "$dir/apt" "$dir/debs" "$dir/lvp_icd.json"
    local apt="$dir/apt"
    mkdir -p "$apt/lists/partial" "$apt/archives/partial" "$apt/sources.list.d" "$apt/preferences.d" "$dir/debs" "$dir/root" || return 1
    local keyring=/usr/share/keyrings/debian-archive-keyring.gpg
    local mirror="${B2DR_DEBIAN_MIRROR:-http://deb.debian.org/debian}"
    {
      echo "deb [signed-by=$keyring] $mirror bookworm main"
      echo "deb [signed-by=$keyring] $mirror $suite main"
    } >"$apt/sources.list"
    local o=(-o "Dir::Etc::sourcelist=$apt/sources.list" -o "Dir::Etc::sourceparts=$apt/sources.list.d"
      -o "Dir::Etc::preferencesparts=$apt/preferences.d" -o "Dir::State::Lists=$apt/lists"
      -o "Dir::Cache=$apt" -o "Dir::Cache::archives=$apt/archives" -o "Debug::NoLocking=1"
      -o "APT::Sandbox::User=$(id -un)" -o "Acquire::Retries=3")
    if ! apt-get "${o[@]}" -qq --error-on=any update >"$dir/apt-update.log" 2>&1; then
      echo "b2dr: Mesa 25 driver: 'apt-get update' of $mirror $suite failed (no network?); see $dir/apt-update.log:" >&2
      tail -5 "$dir/apt-update.log" >&2
      return 1
    fi
    local want="mesa-vulkan-drivers/$suite"
    [ -n "${B2DR_MESA25_PIN:-}" ] && want="mesa-vulkan-drivers=$B2DR_MESA25_PIN"
    local ver
    ver=$(apt-cache "${o[@]}" show "$want" 2>/dev/null | awk '/^Version:/ {print $2; exit}')
    case "$ver" in
      25.*) ;;
      *)
        echo "b2dr: Mesa 25 driver: $suite has mesa-vulkan-drivers '${ver:-none}', not 25.x: update tools/ensure-mesa25.sh" >&2
        return 1
        ;;
    esac
    # the packages to unpack: the driver, and each dependency the system lacks or has older than required
    # (the Vulkan loader is the system's: the driver is loaded by it)
    local pkgs=("mesa-vulkan-drivers=$ver") dep
    while read -r dep; do
      local name="${dep%% *}" need=""
      name="${name%%:*}"
      [ "$name" = libvulkan1 ] && continue
      case "$dep" in *'(>= '*) need="${dep#*(>= }"; need="${need%)*}" ;; esac
      local have
      have=$(dpkg-query -W -f '${Version}' "$name" 2>/dev/null || true)
      if [ -z "$have" ] || { [ -n "$need" ] && dpkg --compare-versions "$have" lt "$need"; }; then
        # the newest version apt knows (backports when bookworm's is too old)
        local cand
        cand=$(apt-cache "${o[@]}" madison "$name" 2>/dev/null | awk -F'|' '{gsub(/ /, "", $2); print $2}' | sort -V | tail -1 || true)
        [ -n "$cand" ] || { echo "b2dr: Mesa 25 driver: no package $name in bookworm / $suite" >&2; return 1; }
        pkgs+=("$name=$cand")
      fi
    done < <(apt-cache "${o[@]}" show "$want" | awk '/^Depends:/ {sub(/^Depends: /, ""); print; exit}' |
      tr ',' '\n' | sed 's/|.*//; s/^ *//; s/ *$//')
    echo "b2dr: downloading ${pkgs[*]}" >&2
    if ! (cd "$dir/debs" && apt-get "${o[@]}" -qq download "${pkgs[@]}" >"$dir/apt-download.log" 2>&1); then
      echo "b2dr: Mesa 25 driver: download of ${pkgs[*]} failed; see $dir/apt-download.log:" >&2
      tail -5 "$dir/apt-download.log" >&2
      return 1
    fi
    local deb
    for deb in "$dir"/debs/*.deb; do dpkg-deb -x "$deb" "$dir/root" || return 1; done
    local so
    so=$(find "$dir/root" -name libvulkan_lvp.so -print -quit)
    [ -n "$so" ] || { echo "b2dr: Mesa 25 driver: no libvulkan_lvp.so in the packages" >&2; return 1; }
    local api
    api=$(sed -n 's/.*"api_version": *"\([^"]*\)".*/\1/p' "$dir/root/usr/share/vulkan/icd.d/lvp_icd.json" 2>/dev/null)
    printf '{\n    "ICD": {\n        "api_version": "%s",\n        "library_path": "%s"\n    },\n    "file_format_version": "1.0.0"\n}\n' \
      "${api:-1.3.0}" "$so" >"$dir/lvp_icd.json" || return 1
    # every library the driver needs resolves (the unpacked ones first)
    local missing
    missing=$(LD_LIBRARY_PATH="$(dirname "$so")" ldd "$so" 2>&1 | grep 'not found' || true)
    if [ -n "$missing" ]; then
      echo "b2dr: Mesa 25 driver: libraries not found for $so:" >&2
      echo "$missing" >&2
      return 1
    fi
    # keep the driver only: the package's other drivers and layers, the .debs and apt's lists go
    find "$dir/root" \( -name 'libvulkan_*.so' ! -name libvulkan_lvp.so -o -name 'libVkLayer_*.so' \) -delete
    rm -rf "$dir/debs" "$apt"
    echo "$ver" >"$stamp" || return 1
  fi
  B2DR_MESA25_ICD="$dir/lvp_icd.json"
  B2DR_MESA25_LIBS=$(dirname "$(sed -n 's/.*"library_path": *"\([^"]*\)".*/\1/p' "$B2DR_MESA25_ICD")")
  B2DR_MESA25_VERSION=$(cat "$stamp")
  export B2DR_MESA25_ICD B2DR_MESA25_LIBS B2DR_MESA25_VERSION
}

if [ "${BASH_SOURCE[0]}" = "$0" ]; then
  b2dr_mesa25
  echo "B2DR_MESA25_ICD=$B2DR_MESA25_ICD"
  echo "B2DR_MESA25_LIBS=$B2DR_MESA25_LIBS"
  echo "B2DR_MESA25_VERSION=$B2DR_MESA25_VERSION"
fi
