# Sourced by scripts/test and scripts/run: installs the Debian packages kdrt needs, if missing.
# kdrt_install_web_test_deps installs the browser test's npm packages from tests/web's lockfile.
# Works on a fresh minimal Debian 12 (bookworm) as root, or with sudo. When every package is
# already installed it does not call apt-get (or sudo) at all.

# curl: scripts/run prints a curl command line to try the server with.
kdrt_packages=(
    ca-certificates g++ make cmake pkg-config git curl
    libtbb-dev libcpp-httplib-dev nlohmann-json3-dev libspdlog-dev libssl-dev
    libopenimageio-dev openimageio-tools python3-imath
    libgtest-dev libgmock-dev libbenchmark-dev
    libembree-dev qemu-user
)
# scripts/test checks the format (clang-format); scripts/lint runs clang-tidy.
kdrt_packages+=(clang-format clang-tidy)
# promtool (in Debian's prometheus package) checks the /metrics exposition in a server test.
kdrt_packages+=(prometheus)
# The scale-out tests (tests/server/scale_out_test.cpp) run Debian's nginx in front of replicas.
kdrt_packages+=(nginx)
# scripts/test validates docker/compose.yaml with `docker-compose config` (offline, no engine).
kdrt_packages+=(docker-compose)
# The client's OpenAPI test validates live answers against proto/openapi.yaml in Python.
# (The ctest openapi_lint also needs node >= 20.19 and npm, which the CI machine image ships and
# Debian 12's nodejs, 18, is too old for; it installs its linter with npm ci. Configure with
# -DKDRT_OPENAPI_LINT=OFF where they are missing.)
kdrt_packages+=(python3 python3-yaml python3-jsonschema)
# The Python client (client/python): numpy, its tests (pytest), and its install test (a venv made
# with --system-site-packages; setuptools and wheel build the package offline).
kdrt_packages+=(python3-numpy python3-pytest python3-venv python3-setuptools python3-wheel)
# The web viewer's browser test (tests/web): Debian's chromium, driven by playwright-core from npm
# on Node.js. Debian's npm is its own package; a nodejs that bundles npm (NodeSource's) conflicts
# with it, so npm is asked for only when no npm is installed.
kdrt_packages+=(chromium nodejs)
# Installed like a daemon (packaging/): the systemd unit's test runs systemd-analyze verify
# (systemd); cpack -G DEB finds the package's Depends with dpkg-shlibdeps (dpkg-dev);
# scripts/deb-install-test installs the .deb into a fresh debootstrap chroot.
kdrt_packages+=(systemd dpkg-dev debootstrap)
if ! command -v npm >/dev/null 2>&1; then
    kdrt_packages+=(npm)
fi

# kdrt_missing_packages: prints the packages of kdrt_packages that are not installed, one a line.
kdrt_missing_packages() {
    local pkg status
    for pkg in "${kdrt_packages[@]}"; do
        # db:Status-Status is "installed" for both "install ok installed" and "hold ok installed".
        # (No "| grep -q": under the callers' pipefail an early grep exit can SIGPIPE dpkg-query.)
        status=$(dpkg-query -W -f='${db:Status-Status}' "$pkg" 2>/dev/null || true)
        if [ "$status" != "installed" ]; then
            echo "$pkg"
        fi
    done
}

kdrt_install_deps() {
    local missing=()
    mapfile -t missing < <(kdrt_missing_packages)
    if [ "${#missing[@]}" -eq 0 ]; then
        return 0
    fi
    echo "kdrt: installing ${missing[*]}"
    local sudo=()
    if [ "$(id -u)" -ne 0 ]; then
        if command -v sudo >/dev/null 2>&1; then
            sudo=(sudo)
        else
            echo "kdrt: missing packages (${missing[*]}) and not root; install them and retry" >&2
            return 1
        fi
    fi
    # "env VAR=..." after sudo: sudo's env_reset would drop a DEBIAN_FRONTEND set in front of it.
    # Lock::Timeout: on a just-booted machine apt-daily/unattended-upgrades may hold the dpkg lock.
    local apt=("${sudo[@]}" env DEBIAN_FRONTEND=noninteractive apt-get
               -o DPkg::Lock::Timeout=600 -o Acquire::Retries=3)
    "${apt[@]}" update -qq || return 1
    "${apt[@]}" install -y -qq --no-install-recommends "${missing[@]}" || return 1
    local still
    still=$(kdrt_missing_packages)
    if [ -n "$still" ]; then
        echo "kdrt: still not installed after apt-get: ${still//$'\n'/ }" >&2
        return 1
    fi
}

# kdrt_install_web_test_deps BUILD_DIR: `npm ci` of tests/web/package-lock.json into
# BUILD_DIR/tests/web (where CMake copied package.json and the lockfile), for the web_viewer test.
# One package (playwright-core, no dependencies); npm takes it from its cache once downloaded.
kdrt_install_web_test_deps() {
    local dir="$1/tests/web"
    if [ ! -f "$dir/package-lock.json" ]; then
        echo "kdrt: $dir/package-lock.json is missing (configure the build first)" >&2
        return 1
    fi
    (cd "$dir" && npm ci --no-audit --no-fund --loglevel=error)
}
