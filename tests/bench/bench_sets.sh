# shellcheck shell=bash disable=SC2034  # its variables are for the scripts that source it
# Shared by run.sh and levers.sh (sourced, not run): the standard table's scenes and ray sets.
#
#   bench_sets_init RESULTS_NAME "$@"
#       takes the script's arguments, BUILD_DIR [WORK_DIR] (default BUILD_DIR/bench-rays): prints
#       the script's header comment and exits 2 on -h, --help or a wrong count; sets build_dir,
#       bench, data_dir, work_dir, res (RES, default 1024), scenes (SCENES), kinds and results
#       (WORK_DIR/RESULTS_NAME, emptied); exits 1 if kdrt-bench is not built
#   bench_make_scenes         writes the generated scenes (stadium, 16 and 64 bunnies) to WORK_DIR once
#   bench_scene SCENE         sets mesh, stem (the ray sets' name) and camera (kdrt-bench rays options)
#   bench_rays KIND           the path of the current scene's KIND set, generated when missing
#   json_get LINE KEY         the value of a top-level key in a flat JSON line (strings unquoted)

bench_sets_init() {
    local name=$1
    shift
    if [[ $# -lt 1 || $# -gt 2 || "$1" == "-h" || "$1" == "--help" ]]; then
        sed -n '2,/^set /s/^# \{0,1\}//p' "$0" >&2
        exit 2
    fi
    build_dir=$1
    bench=$build_dir/tests/bench/kdrt-bench
    work_dir=${2:-$build_dir/bench-rays}
    data_dir=$(cd "$(dirname "${BASH_SOURCE[0]}")/../data" && pwd)
    res=${RES:-1024}
    read -r -a scenes <<< "${SCENES:-bunny00.off ChineseDragon-10kv.off diplodocus.off stadium.ply bunny16.ply bunny64.ply}"
    kinds=(primary shadow diffuse random)
    if [[ ! -x "$bench" ]]; then
        echo "$(basename "$0"): $bench not found; build it with: cmake --build $build_dir --target kdrt-bench" >&2
        exit 1
    fi
    mkdir -p "$work_dir"
    results=$work_dir/$name
    : > "$results"
}

bench_make_scenes() {
    if [[ ! -s "$work_dir/stadium.ply" ]]; then
        "$bench" scene stadium --out "$work_dir/stadium.ply" >> "$results"
    fi
    local copies
    for copies in 16 64; do
        if [[ ! -s "$work_dir/bunny$copies.ply" ]]; then
            "$bench" scene grid --from "$data_dir/bunny00.off" --copies $copies \
                --out "$work_dir/bunny$copies.ply" >> "$results"
        fi
    done
}

bench_scene() {
    mesh=$data_dir/$1
    [[ -f "$mesh" ]] || mesh=$work_dir/$1
    stem=${1%.*}
    camera=()
    # The stadium's camera stands inside it, near the "teapot" (a unit sphere at (0.3, -0.2, 0.1)):
    # from the default view outside, every ray would stop at the closed box's 12 triangles.
    if [[ $stem == stadium ]]; then
        # shellcheck disable=SC2054  # the commas are part of the values
        camera=(--eye 1.7,0.8,4.1 --look-at 0.3,-0.2,0.1)
        stem=stadium-inside
    fi
}

bench_rays() {
    local rays_file=$work_dir/$stem.$1.$res.kdrr
    if [[ ! -s "$rays_file" ]]; then
        echo "$(basename "$0"): generating $rays_file" >&2
        "$bench" rays "$mesh" --kind "$1" --res "$res" "${camera[@]}" --out "$rays_file" >> "$results"
    fi
    echo "$rays_file"
}

json_get() {
    sed -n "s/.*\"$2\":\(\"[^\"]*\"\|[^,}]*\).*/\1/p" <<< "$1" | tr -d '"'
}
