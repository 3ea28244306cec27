# Sourced by scripts/test and scripts/run: installs the Debian packages kdrt needs, if missing.
# Works on a fresh minimal Debian 12 (bookworm) as root, or with sudo.

kdrt_packages=(
    ca-certificates g++ make cmake pkg-config git
    libtbb-dev libcpp-httplib-dev nlohmann-json3-dev libspdlog-dev libssl-dev
    libopenimageio-dev openimageio-tools python3-imath
    libgtest-dev libgmock-dev libbenchmark-dev
    libembree-dev qemu-user
)

kdrt_install_deps() {
    local missing=()
    local pkg
    for pkg in "${kdrt_packages[@]}"; do
        if ! dpkg-query -W -f='${Status}' "$pkg" 2>/dev/null | grep -q "install ok installed"; then
            missing+=("$pkg")
        fi
    done
    if [ "${#missing[@]}" -eq 0 ]; then
        return 0
    fi
    echo "kdrt: installing ${missing[*]}"
    local sudo=""
    if [ "$(id -u)" -ne 0 ]; then
        if command -v sudo >/dev/null 2>&1; then
            sudo="sudo"
        else
            echo "kdrt: missing packages (${missing[*]}) and not root; install them and retry" >&2
            return 1
        fi
    fi
    $sudo apt-get update -qq
    DEBIAN_FRONTEND=noninteractive $sudo apt-get install -y -qq --no-install-recommends "${missing[@]}"
}
