# Integration test of kdrt-bench (cmake -P). Inputs: BENCH (the executable), MESH, WORK_DIR,
# EMBREE (ON when built with --compare embree). Fails with FATAL_ERROR naming what is wrong.

foreach(var BENCH MESH WORK_DIR)
    if(NOT DEFINED ${var})
        message(FATAL_ERROR "check_bench.cmake: -D${var}=... is required")
    endif()
endforeach()
file(MAKE_DIRECTORY "${WORK_DIR}")

# run_bench(OUT_VAR args...): runs kdrt-bench, requires exit 0 and exactly one output line.
function(run_bench out_var)
    execute_process(COMMAND "${BENCH}" ${ARGN}
                    RESULT_VARIABLE rc OUTPUT_VARIABLE out ERROR_VARIABLE err
                    OUTPUT_STRIP_TRAILING_WHITESPACE)
    if(NOT rc EQUAL 0)
        message(FATAL_ERROR "kdrt-bench ${ARGN} exited with ${rc}\nstdout: ${out}\nstderr: ${err}")
    endif()
    if(out MATCHES "\n")
        message(FATAL_ERROR "kdrt-bench ${ARGN} printed more than one line:\n${out}")
    endif()
    set(${out_var} "${out}" PARENT_SCOPE)
endfunction()

# expect_keys(JSON keys...): every key exists and is not null.
function(expect_keys json)
    string(JSON type ERROR_VARIABLE err TYPE "${json}")
    if(err OR NOT type STREQUAL "OBJECT")
        message(FATAL_ERROR "not a JSON object: ${json}\n${err}")
    endif()
    foreach(key ${ARGN})
        string(JSON type ERROR_VARIABLE err TYPE "${json}" ${key})
        if(err OR type STREQUAL "NULL")
            message(FATAL_ERROR "key '${key}' is missing from: ${json}")
        endif()
    endforeach()
endfunction()

# expect_value(JSON key value)
function(expect_value json key want)
    string(JSON got GET "${json}" ${key})
    if(NOT got STREQUAL want)
        message(FATAL_ERROR "key '${key}' is '${got}', expected '${want}', in: ${json}")
    endif()
endfunction()

# expect_failure(CODE STDERR_PATTERN args...): kdrt-bench must exit with CODE and say PATTERN.
function(expect_failure code pattern)
    execute_process(COMMAND "${BENCH}" ${ARGN} RESULT_VARIABLE rc OUTPUT_VARIABLE out ERROR_VARIABLE err)
    if(NOT rc EQUAL code)
        message(FATAL_ERROR "kdrt-bench ${ARGN}: exit ${rc}, expected ${code}\nstderr: ${err}")
    endif()
    if(NOT err MATCHES "${pattern}")
        message(FATAL_ERROR "kdrt-bench ${ARGN}: stderr does not match '${pattern}':\n${err}")
    endif()
endfunction()

set(primary "${WORK_DIR}/primary64.kdrr")
set(shadow "${WORK_DIR}/shadow64.kdrr")
set(hits "${WORK_DIR}/primary64.kdrh")
set(occl "${WORK_DIR}/shadow64.kdro")
file(REMOVE "${primary}" "${shadow}" "${hits}" "${occl}")

# build
run_bench(build_line build "${MESH}" --reps 2 --threads 2)
expect_keys("${build_line}" triangles node_bytes nodes leaves empty_leaves max_depth mean_leaf_depth
            mean_tris_per_leaf sah_cost bytes bytes_per_triangle build_ms builder threads parse_ms
            cpu_util)
expect_value("${build_line}" node_bytes 8)
expect_value("${build_line}" builder sah)
expect_value("${build_line}" threads 2)
run_bench(middle_line build "${MESH}" --builder middle --threads 1)
expect_value("${middle_line}" builder middle)
# --c-isect reaches the builder: a dearer triangle test gives a deeper tree with more nodes.
run_bench(default_cost_line build "${MESH}" --threads 1)
run_bench(dear_isect_line build "${MESH}" --c-isect 3 --threads 1)
expect_value("${dear_isect_line}" c_isect 3.0)
string(JSON default_nodes GET "${default_cost_line}" nodes)
string(JSON dear_nodes GET "${dear_isect_line}" nodes)
if(NOT dear_nodes GREATER default_nodes)
    message(FATAL_ERROR "--c-isect 3 gave ${dear_nodes} nodes, the default ${default_nodes}: expected more")
endif()
# --out writes the tree's blob with its build time zeroed: the same tree gives the same bytes (two
# builds, one and two threads), another tree (--c-isect 3) other bytes.
set(blob_one "${WORK_DIR}/tree_one.blob")
set(blob_two "${WORK_DIR}/tree_two.blob")
set(blob_dear "${WORK_DIR}/tree_dear.blob")
run_bench(out_one_line build "${MESH}" --threads 1 --out "${blob_one}")
run_bench(out_two_line build "${MESH}" --threads 2 --reps 2 --out "${blob_two}")
run_bench(out_dear_line build "${MESH}" --threads 1 --c-isect 3 --out "${blob_dear}")
file(SIZE "${blob_one}" blob_bytes)
if(blob_bytes LESS 1000)
    message(FATAL_ERROR "build --out wrote ${blob_bytes} bytes")
endif()
file(SHA256 "${blob_one}" blob_one_hash)
file(SHA256 "${blob_two}" blob_two_hash)
file(SHA256 "${blob_dear}" blob_dear_hash)
if(NOT blob_one_hash STREQUAL blob_two_hash)
    message(FATAL_ERROR "build --out: two builds of one tree wrote different blobs")
endif()
if(blob_one_hash STREQUAL blob_dear_hash)
    message(FATAL_ERROR "build --out: --c-isect 3 wrote the default tree's blob")
endif()
file(REMOVE "${blob_one}" "${blob_two}" "${blob_dear}")
expect_failure(2 "option '--c-isect': 'nan' is not a number" build "${MESH}" --c-isect nan)
expect_failure(2 "option '--c-isect': '0' is not a number" build "${MESH}" --c-isect 0)

# rays
set(rays_keys kind res seed rays occlusion out bytes)
run_bench(rays_line rays "${MESH}" --kind primary --res 64 --out "${primary}")
expect_keys("${rays_line}" ${rays_keys})
expect_value("${rays_line}" camera default)
# A given camera: the rays start at its eye.
run_bench(camera_line rays "${MESH}" --kind primary --res 8 --eye 0.25,0.5,3 --look-at 0,0,0 --out "${WORK_DIR}/cam8.kdrr")
expect_value("${camera_line}" camera "eye 0.25,0.5,3 look_at 0,0,0")
file(READ "${WORK_DIR}/cam8.kdrr" cam8_hex HEX OFFSET 16 LIMIT 12)
if(NOT cam8_hex STREQUAL "0000803e0000003f00004040")  # 0.25f 0.5f 3.0f, little-endian
    message(FATAL_ERROR "--eye 0.25,0.5,3: the first ray starts at ${cam8_hex}")
endif()
expect_value("${rays_line}" rays 4096)
file(SIZE "${primary}" primary_size)
if(NOT primary_size EQUAL 131088)  # 16 + 4096 * 32
    message(FATAL_ERROR "${primary} has ${primary_size} bytes, expected 131088")
endif()
run_bench(shadow_line rays "${MESH}" --kind shadow --res 64 --seed 7 --out "${shadow}")
expect_value("${shadow_line}" occlusion ON)  # CMake renders JSON true as ON

# trace
set(trace_keys rays occlusion mode threads isa packets packet_rays single_rays sorted_rays builder reps parse_ms
               build_ms seconds seconds_min mrays_per_s hits cpu_util)
run_bench(trace_line trace "${MESH}" "${primary}" --reps 2 --threads 2 --out "${hits}")
expect_keys("${trace_line}" ${trace_keys})
expect_value("${trace_line}" rays 4096)
expect_value("${trace_line}" mode auto)
expect_value("${trace_line}" occlusion OFF)
string(JSON hit_count GET "${trace_line}" hits)
if(hit_count LESS_EQUAL 0 OR hit_count GREATER_EQUAL 4096)
    message(FATAL_ERROR "a framed bunny should be hit by some but not all primary rays: ${trace_line}")
endif()
file(SIZE "${hits}" hits_size)
if(NOT hits_size EQUAL 65552)  # 16 + 4096 * 16
    message(FATAL_ERROR "${hits} has ${hits_size} bytes, expected 65552")
endif()
# Every mode and instruction set writes the same answers, byte for byte.
foreach(variant "single;scalar" "packet;sse4" "packet;avx2" "packet;avx512")
    list(GET variant 0 variant_mode)
    list(GET variant 1 variant_isa)
    execute_process(COMMAND ${BENCH} trace "${MESH}" "${primary}" --reps 1 --mode ${variant_mode} --isa ${variant_isa}
                            --out "${hits}.${variant_mode}.${variant_isa}"
                    RESULT_VARIABLE variant_rc OUTPUT_VARIABLE variant_line ERROR_VARIABLE variant_err)
    if(variant_rc EQUAL 1 AND variant_err MATCHES "not supported by this CPU")
        continue()
    endif()
    if(NOT variant_rc EQUAL 0)
        message(FATAL_ERROR "trace --mode ${variant_mode} --isa ${variant_isa} failed: ${variant_err}")
    endif()
    expect_value("${variant_line}" mode ${variant_mode})
    expect_value("${variant_line}" isa ${variant_isa})
    file(SHA256 "${hits}" want_sum)
    file(SHA256 "${hits}.${variant_mode}.${variant_isa}" got_sum)
    if(NOT want_sum STREQUAL got_sum)
        message(FATAL_ERROR "--mode ${variant_mode} --isa ${variant_isa} wrote different hits than --mode auto")
    endif()
endforeach()
run_bench(occl_line trace "${MESH}" "${shadow}" --reps 1 --threads 1 --out "${occl}")
expect_keys("${occl_line}" ${trace_keys})
expect_value("${occl_line}" occlusion ON)
string(JSON shadow_rays GET "${shadow_line}" rays)
expect_value("${occl_line}" rays ${shadow_rays})

# --stats: the work per ray from the counting kernels; the answers stay the same
run_bench(stats_line trace "${MESH}" "${primary}" --reps 1 --stats --out "${WORK_DIR}/stats_hits.kdrh")
expect_keys("${stats_line}" ${trace_keys} steps_per_ray leaves_per_ray tri_tests_per_ray packet_visits
            lane_utilisation)
string(JSON steps GET "${stats_line}" steps_per_ray)
string(JSON use GET "${stats_line}" lane_utilisation)
if(NOT steps GREATER 1 OR use GREATER 1)
    message(FATAL_ERROR "--stats: a framed bunny's primary rays take more than one step each, and "
                        "no more lanes than a packet has: ${stats_line}")
endif()
file(SHA256 "${hits}" plain_sum)
file(SHA256 "${WORK_DIR}/stats_hits.kdrh" stats_sum)
if(NOT plain_sum STREQUAL stats_sum)
    message(FATAL_ERROR "--stats changed the answers")
endif()
string(JSON plain_steps ERROR_VARIABLE no_steps GET "${trace_line}" steps_per_ray)
if(NOT no_steps)
    message(FATAL_ERROR "steps_per_ray without --stats: ${trace_line}")
endif()
expect_failure(2 "takes no value" trace "${MESH}" "${primary}" --stats=yes)

if(EMBREE)
    run_bench(embree_line trace "${MESH}" "${primary}" --reps 1 --compare embree)
    expect_keys("${embree_line}" ${trace_keys} embree_mrays_per_s embree_best_mode ratio
                embree_build_ms embree_bytes_per_triangle differences embree_best_flags
                embree_default_mrays_per_s embree_robust_mrays_per_s embree_robust_best_mode
                ratio_robust embree_robust_build_ms embree_robust_differences embree_version)
    # Both scene flags measured: the default's modes unprefixed, the robust scene's prefixed.
    if(NOT embree_line MATCHES "\"intersect1\":" OR NOT embree_line MATCHES "\"robust_intersect1\":")
        message(FATAL_ERROR "--compare embree must time both scene flags: ${embree_line}")
    endif()
endif()

# generated scenes
run_bench(grid_line scene grid --from "${MESH}" --copies 2 --out "${WORK_DIR}/grid.ply")
expect_value("${grid_line}" triangles 150816)
run_bench(grid_build build "${WORK_DIR}/grid.ply")
expect_value("${grid_build}" triangles 150816)
run_bench(stadium_line scene stadium --out "${WORK_DIR}/stadium.ply")
expect_value("${stadium_line}" triangles 128892)
expect_failure(2 "not one of stadium, grid" scene bogus --out "${WORK_DIR}/x.ply")

# distance: the JSON keys, and the kD answers equal to brute force on the subset
set(distance_keys mesh triangles closed threads reps points build_ms surface_ms kd_points_per_s
                  kd_uniform_points_per_s kd_near_points_per_s signed_points_per_s
                  signed_uniform_points_per_s signed_near_points_per_s brute_points brute_seconds
                  brute_points_per_s ratio cpu_util matches_brute_force mismatches)
run_bench(distance_line distance "${MESH}" --points 2000 --brute 64 --reps 1 --threads 2)
expect_keys("${distance_line}" ${distance_keys})
expect_value("${distance_line}" points 2000)
expect_value("${distance_line}" brute_points 64)
expect_value("${distance_line}" closed ON)
expect_value("${distance_line}" matches_brute_force ON)
expect_value("${distance_line}" mismatches 0)
expect_failure(2 "--points" distance "${MESH}" --points 1)
expect_failure(2 "--brute" distance "${MESH}" --points 100 --brute 101)
expect_failure(2 "missing argument MESH" distance)

# render: the JSON keys, the image through the kdrt-image helper, and secondary-ray shadings
set(render_png "${WORK_DIR}/render64.png")
file(REMOVE "${render_png}")
set(render_keys shading width height spp tile isa threads builder reps build_ms pixels rays seconds
                seconds_min fps mrays_per_s cpu_util batch_rays batch_seconds batch_mrays_per_s)
run_bench(render_line render "${MESH}" --res 64 --reps 1 --threads 2 --out "${render_png}")
expect_keys("${render_line}" ${render_keys} overhead out)
expect_value("${render_line}" shading eyelight)
expect_value("${render_line}" pixels 4096)
expect_value("${render_line}" rays 4096)
expect_value("${render_line}" batch_rays 4096)
if(NOT EXISTS "${render_png}")
    message(FATAL_ERROR "render --out did not write ${render_png}")
endif()
file(READ "${render_png}" png_magic LIMIT 8 HEX)
if(NOT png_magic STREQUAL "89504e470d0a1a0a")
    message(FATAL_ERROR "${render_png} is not a PNG (starts with ${png_magic})")
endif()
run_bench(ao_line render "${MESH}" --shading ao --ao-samples 2 --res 32 --spp 2 --tile 8 --reps 1)
expect_keys("${ao_line}" ${render_keys})
string(JSON ao_rays GET "${ao_line}" rays)
if(ao_rays LESS_EQUAL 2048)  # 32 x 32 x 2 camera rays, plus 2 AO rays per camera hit
    message(FATAL_ERROR "ao should trace occlusion rays besides the camera rays: ${ao_line}")
endif()
string(JSON ao_overhead ERROR_VARIABLE no_overhead GET "${ao_line}" overhead)
if(NOT no_overhead)
    message(FATAL_ERROR "overhead is only defined for camera-ray-only shadings: ${ao_line}")
endif()
if(EMBREE)
    run_bench(render_embree_line render "${MESH}" --res 64 --reps 1 --compare embree)
    expect_keys("${render_embree_line}" ${render_keys} embree_mrays_per_s embree_best_mode embree_fps ratio
                differences ratio_robust embree_robust_mrays_per_s)
endif()

# scene instances: a small two-level scene against the merged mesh (and Embree's instancing)
set(scene_keys command kind instances bytes_per_instance pose_update_ms scene_build_ms top_nodes kinds)
set(kind_keys kind rays merged_mrays_per_s scene_mrays_per_s ratio_vs_merged cpu_util
    differences_vs_merged)
set(scene_compare)
if(EMBREE)
    set(scene_compare --compare embree)
    list(APPEND scene_keys embree_pose_update_ms)
    list(APPEND kind_keys embree_mrays_per_s embree_best_mode ratio_vs_embree differences_vs_embree)
endif()
run_bench(scene_line scene instances --from sphere --copies 9 --res 32 --reps 1 ${scene_compare})
expect_keys("${scene_line}" ${scene_keys})
expect_value("${scene_line}" instances 9)
foreach(k 0 1 2 3)  # primary, shadow, diffuse, random
    string(JSON kind_line GET "${scene_line}" kinds ${k})
    expect_keys("${kind_line}" ${kind_keys})
endforeach()
expect_failure(2 "--compare" scene instances --from sphere --compare optix)

# exit codes: 2 for the command line, 1 for a failed run naming the file
expect_failure(2 "missing argument RAYS.kdrr" trace "${MESH}")
expect_failure(2 "unknown option '--bogus'" build "${MESH}" --bogus 1)
expect_failure(2 "--kind" rays "${MESH}" --kind sideways --out "${WORK_DIR}/x.kdrr")
expect_failure(2 "option '--look-at' is required with '--eye'" rays "${MESH}" --kind primary --eye 0,0,5 --out "${WORK_DIR}/x.kdrr")
expect_failure(2 "option '--eye': '0,0' is not X,Y,Z" rays "${MESH}" --kind primary --eye 0,0 --look-at 0,0,0 --out "${WORK_DIR}/x.kdrr")
expect_failure(2 "options '--eye'/'--look-at'" rays "${MESH}" --kind primary --eye 1,2,3 --look-at 1,2,3 --out "${WORK_DIR}/x.kdrr")
expect_failure(2 "--reps" trace "${MESH}" "${primary}" --reps 0)
expect_failure(2 "unknown command" frobnicate)
expect_failure(1 "no-such-mesh.off" build "${WORK_DIR}/no-such-mesh.off")
expect_failure(2 "--mode" trace "${MESH}" "${primary}" --mode sideways)
expect_failure(2 "--isa" trace "${MESH}" "${primary}" --isa avx3)
expect_failure(1 "cannot read rays from .*bunny00.off" trace "${MESH}" "${MESH}")
expect_failure(2 "--shading" render "${MESH}" --shading glossy)
expect_failure(2 "--tile" render "${MESH}" --tile 12)
expect_failure(1 "frame.bmp" render "${MESH}" --res 8 --reps 1 --out "${WORK_DIR}/frame.bmp")

message(STATUS "kdrt-bench integration: all checks passed")
