#!/usr/bin/env bash
# What issue 23's kernel levers give, measured in one run, as Markdown: for each scene and ray set
# of the standard table (run.sh), the traversal modes side by side, and for the shadow set the
# same rays traced by the closest-hit kernel instead of the occlusion (any-hit) kernel.
#
#   tests/bench/levers.sh BUILD_DIR [WORK_DIR]
#
# Columns (Mrays/s, median of REPS passes, THREADS threads):
#   auto     the default policy: packets where rays are coherent, single rays in turn elsewhere
#   packet   every ray in packets (--mode packet)
#   single   every ray walked alone over the wide kD nodes, twelve in turn (--mode single)
#   one      one ray at a time through the public single-ray call (--mode one), the counterpart
#            of rtcIntersect1 / rtcOccluded1; with COMPARE=embree, on the diffuse and random sets,
#            also Embree's fastest one-ray mode and the ratio (the issue's single-ray goal)
#   closest  shadow set only: the same rays with the occlusion flag cleared (a copy), so the
#            closest-hit kernel traces them (auto); auto / closest is what the occlusion kernel
#            gives over closest hit
# WORK_DIR holds the ray sets as run.sh writes them (the same default, BUILD_DIR/bench-rays); a
# missing set or generated scene is made as run.sh makes it (bench_sets.sh). Tunables
# (environment): REPS=5, THREADS=2, RES=1024, SCENES="..." (as run.sh), COMPARE=embree.
# Progress goes to stderr, the raw JSON lines to WORK_DIR/levers.jsonl.
set -euo pipefail

# shellcheck source=tests/bench/bench_sets.sh
source "$(dirname "$0")/bench_sets.sh"
bench_sets_init levers.jsonl "$@"
reps=${REPS:-5}
threads=${THREADS:-2}
compare=${COMPARE:-}

# trace MESH RAYS ARGS...: one kdrt-bench trace line, kept in levers.jsonl.
trace() {
    local line
    line=$("$bench" trace "$1" "$2" --threads "$threads" --reps "$reps" "${@:3}")
    echo "$line" >> "$results"
    echo "$line"
}

# closest_copy SET: the set with its KDRR flags (bytes 6-7) cleared, so it is traced for closest hits.
closest_copy() {
    local copy
    copy=$work_dir/$(basename "${1%.kdrr}").closest.kdrr
    if [[ ! -s "$copy" || "$copy" -ot "$1" ]]; then
        cp "$1" "$copy.tmp"
        printf '\0\0' | dd of="$copy.tmp" bs=1 seek=6 conv=notrunc status=none
        mv "$copy.tmp" "$copy"
    fi
    echo "$copy"
}

echo "| scene | ray set | auto | packet | single | one | one / Embree one (mode) | closest-hit kernel on the shadow rays |"
echo "|---|---|---|---|---|---|---|---|"
bench_make_scenes
for scene in "${scenes[@]}"; do
    bench_scene "$scene"
    for kind in "${kinds[@]}"; do
        rays_file=$(bench_rays "$kind")
        echo "levers.sh: $stem $kind" >&2
        row="| $stem | $kind |"
        for mode in auto packet single; do
            row+=" $(json_get "$(trace "$mesh" "$rays_file" --mode "$mode")" mrays_per_s) |"
        done
        one_args=(--mode one)
        if [[ -n $compare && ( $kind == diffuse || $kind == random ) ]]; then
            one_args+=(--compare "$compare")
        fi
        line=$(trace "$mesh" "$rays_file" "${one_args[@]}")
        row+=" $(json_get "$line" mrays_per_s) |"
        if [[ ${#one_args[@]} -gt 2 ]]; then
            row+=" $(json_get "$line" ratio_1) ($(json_get "$line" embree_1_mode)) |"
        else
            row+=" |"
        fi
        if [[ $kind == shadow ]]; then
            row+=" $(json_get "$(trace "$mesh" "$(closest_copy "$rays_file")" --mode auto)" mrays_per_s) |"
        else
            row+=" |"
        fi
        echo "$row"
    done
done
