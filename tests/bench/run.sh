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

# shellcheck source=tests/bench/bench_sets.sh
source "$(dirname "$0")/bench_sets.sh"
bench_sets_init results.jsonl "$@"
reps=${REPS:-9}
build_reps=${BUILD_REPS:-3}
threads_list=${THREADS:-"1 2"}
mode=${MODE:-auto}
compare=${COMPARE:-}

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

bench_make_scenes

for scene in "${scenes[@]}"; do
    bench_scene "$scene"
    build_line=$("$bench" build "$mesh" --reps "$build_reps")
    echo "$build_line" >> "$results"
    triangles=$(json_get "$build_line" triangles)
    build_ms=$(json_get "$build_line" build_ms)
    bytes_per_tri=$(json_get "$build_line" bytes_per_triangle)
    for kind in "${kinds[@]}"; do
        rays_file=$(bench_rays "$kind")
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
