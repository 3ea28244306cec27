#!/usr/bin/env bash
# The standard kdrt benchmark table, as Markdown: the bunny (75k triangles), dragon-10kv (20k),
# diplodocus (48k), a generated teapot-in-a-stadium (129k, seen from inside), 16 bunnies (1.2M)
# and 64 bunnies (4.8M), each with four ray sets (primary, shadow, diffuse, random) on 1 and 2
# threads.
#
#   tests/bench/run.sh BUILD_DIR [WORK_DIR]
#
# BUILD_DIR holds tests/bench/kdrt-bench. Ray sets are written to WORK_DIR (default
# BUILD_DIR/bench-rays) and reused when already there. Tunables (environment):
#   RES=1024        image resolution of the ray sets (res x res primary and random rays)
#   REPS=9          timed passes per trace (median reported; short sets need several to settle)
#   BUILD_REPS=3    timed builds per scene (median reported)
#   THREADS="1 2"   thread counts, one column each
#   MODE=auto       traversal mode passed to kdrt-bench trace (auto|packet|single)
#   SCENES="..."    scene names to run (default: all six; e.g. SCENES="bunny00.off")
#   COMPARE=embree  also trace with Embree (if kdrt-bench was built with it) and add its columns:
#                   its best over both scene flags (the goals' yardstick), its robust (watertight)
#                   scene alone, and the default scene's RTC_BUILD_QUALITY_HIGH build time
# The table goes to stdout, progress to stderr; the raw JSON lines are kept in WORK_DIR/results.jsonl.
set -euo pipefail

if [[ $# -lt 1 || $# -gt 2 || "$1" == "-h" || "$1" == "--help" ]]; then
    sed -n '2,18s/^# \{0,1\}//p' "$0" >&2
    exit 2
fi
build_dir=$1
work_dir=${2:-$build_dir/bench-rays}
bench=$build_dir/tests/bench/kdrt-bench
data_dir=$(cd "$(dirname "$0")/../data" && pwd)
res=${RES:-1024}
reps=${REPS:-9}
build_reps=${BUILD_REPS:-3}
threads_list=${THREADS:-"1 2"}
mode=${MODE:-auto}
compare=${COMPARE:-}
read -r -a scenes <<< "${SCENES:-bunny00.off ChineseDragon-10kv.off diplodocus.off stadium.ply bunny16.ply bunny64.ply}"
kinds=(primary shadow diffuse random)

if [[ ! -x "$bench" ]]; then
    echo "run.sh: $bench not found; build it with: cmake --build $build_dir --target kdrt-bench" >&2
    exit 1
fi
mkdir -p "$work_dir"
results=$work_dir/results.jsonl
: > "$results"

# json_get LINE KEY: the value of a top-level key in a flat JSON line (strings unquoted).
json_get() {
    sed -n "s/.*\"$2\":\(\"[^\"]*\"\|[^,}]*\).*/\1/p" <<< "$1" | tr -d '"'
}

columns=(scene triangles "build ms" "ray set" rays "hit %")
for t in $threads_list; do columns+=("${t}T Mrays/s"); done
if [[ -n $compare ]]; then
    for t in $threads_list; do
        columns+=("Embree ${t}T Mrays/s (mode)" "kdrt/Embree ${t}T" "Embree robust ${t}T Mrays/s" "kdrt/robust ${t}T")
    done
    columns+=("Embree build ms" "bytes/tri kdrt / Embree" "differences (ties, kdrt = oracle)")
fi
printf '| %s ' "${columns[@]}"
echo "|"
printf '|---%.0s' "${columns[@]}"
echo "|"

# The generated scenes live in WORK_DIR, made once.
if [[ ! -s "$work_dir/stadium.ply" ]]; then
    "$bench" scene stadium --out "$work_dir/stadium.ply" >> "$results"
fi
for copies in 16 64; do
    if [[ ! -s "$work_dir/bunny$copies.ply" ]]; then
        "$bench" scene grid --from "$data_dir/bunny00.off" --copies $copies \
            --out "$work_dir/bunny$copies.ply" >> "$results"
    fi
done

for scene in "${scenes[@]}"; do
    mesh=$data_dir/$scene
    [[ -f "$mesh" ]] || mesh=$work_dir/$scene
    stem=${scene%.*}
    # The stadium's camera stands inside it, near the "teapot" (a unit sphere at (0.3, -0.2, 0.1)):
    # from the default view outside, every ray would stop at the closed box's 12 triangles.
    camera=()
    if [[ $stem == stadium ]]; then
        camera=(--eye 1.7,0.8,4.1 --look-at 0.3,-0.2,0.1)
        stem=stadium-inside
    fi
    build_line=$("$bench" build "$mesh" --reps "$build_reps")
    echo "$build_line" >> "$results"
    triangles=$(json_get "$build_line" triangles)
    build_ms=$(json_get "$build_line" build_ms)
    bytes_per_tri=$(json_get "$build_line" bytes_per_triangle)
    for kind in "${kinds[@]}"; do
        rays_file=$work_dir/$stem.$kind.$res.kdrr
        if [[ ! -s "$rays_file" ]]; then
            echo "run.sh: generating $rays_file" >&2
            "$bench" rays "$mesh" --kind "$kind" --res "$res" "${camera[@]}" --out "$rays_file" >> "$results"
        fi
        speeds=""
        embree_cols=""
        rays=0
        hit_pct=0
        for t in $threads_list; do
            echo "run.sh: $scene $kind, $t thread(s)" >&2
            args=(trace "$mesh" "$rays_file" --threads "$t" --reps "$reps" --mode "$mode")
            [[ -n $compare ]] && args+=(--compare "$compare")
            line=$("$bench" "${args[@]}")
            echo "$line" >> "$results"
            rays=$(json_get "$line" rays)
            hits=$(json_get "$line" hits)
            hit_pct=$(awk -v h="$hits" -v n="$rays" 'BEGIN { printf "%.1f", (n > 0 ? 100 * h / n : 0) }')
            speeds+=" $(json_get "$line" mrays_per_s) |"
            if [[ -n $compare ]]; then
                embree_cols+=" $(json_get "$line" embree_mrays_per_s) ($(json_get "$line" embree_best_mode)) |"
                embree_cols+=" $(json_get "$line" ratio) |"
                embree_cols+=" $(json_get "$line" embree_robust_mrays_per_s) |"
                embree_cols+=" $(json_get "$line" ratio_robust) |"
            fi
        done
        if [[ -n $compare ]]; then  # from the last thread count's run
            embree_cols+=" $(json_get "$line" embree_build_ms) |"
            embree_cols+=" $bytes_per_tri / $(json_get "$line" embree_bytes_per_triangle) |"
            embree_cols+=" $(json_get "$line" differences) ($(json_get "$line" ties), $(json_get "$line" kdrt_matches_oracle)) |"
        fi
        echo "| $stem | $triangles | $build_ms | $kind | $rays | $hit_pct |$speeds$embree_cols"
    done
done
