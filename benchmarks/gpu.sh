#!/usr/bin/env bash
# Every GPU check of the project in few calls of the device machine (see docs/guide/gpu.md).
#
#   bash benchmarks/gpu.sh tests   # the tests' CUDA variants and the functional tests (default
#                                  # device: the GPU), then the quick benchmarks
#   bash benchmarks/gpu.sh big     # the DRT weight-build profile, M by both methods, live M by
#                                  # both, L by MLOS-MART (about 9 minutes)
#   bash benchmarks/gpu.sh profile # the correlation tests and benchmark, the weight-build profile
#   bash benchmarks/gpu.sh iter    # the unit tests' CUDA variants, S and M reconstructions, live M by
#                                  # MLOS-MART (about 8 minutes)
#   bash benchmarks/gpu.sh live    # live M by MLOS-MART, live S by both, L by MLOS-MART, then the CUDA
#                                  # and functional tests (about 8 minutes)
#   bash benchmarks/gpu.sh corr    # the correlation's tests, and its benchmark in every variant with
#                                  # a kernel profile (about 6 minutes)
#   bash benchmarks/gpu.sh monitor # the elimination and live tests' CUDA variants, live M by MLOS-MART at
#                                  # the rig's PVR and two monitoring PVRs, M by MLOS-MART (about 8 min)
#   bash benchmarks/gpu.sh quality # Q at the chapter's 400 iterations: M by DRT-MART and MLOS-MART, the
#                                  # dual-camera Mc2 and S2 by all three methods; Mc2 at 1 PPM (about 8 min)
#   bash benchmarks/gpu.sh fly     # weights made on the fly: their CUDA tests, M by MLOS-MART with stored and
#                                  # with on-the-fly weights, L by MLOS-MART (part on the fly; about 9 min)
#   bash benchmarks/gpu.sh batch   # a whole run of M: volumes written behind the reconstruction and
#                                  # read ahead of the correlation, against one after the other (~6 min)
#   bash benchmarks/gpu.sh matrixfree # the matrix-free projector: its CUDA tests, S and Mc by both
#                                  # projectors, M by it at 400 iterations (goal <= 2 s), live M by it
#                                  # (goal 10 pairs/s), and the per-voxel rate of L's templates applied
#                                  # in every iteration on 23 of its planes (goal: L at 400 its <= 60 s;
#                                  # about 9 minutes)
#   bash benchmarks/gpu.sh tomo    # Tomo-PIV: the pinhole projector's CUDA tests and the Tomo functional
#                                  # tests, T4, T6, T8 by MLOS-SMART and the MART baseline, then
#                                  # lfpiv study lf-vs-tomo --scale quick on the GPU (about 8 minutes)
#   bash benchmarks/gpu.sh slabs   # depth slabs: their CUDA tests (reconstruction and correlation), the
#                                  # slab path against the in-memory one on the GPU at two sizes, and a
#                                  # 256 x 256 x 512 pair correlated in 8 slabs (about 6 minutes)
#   bash benchmarks/gpu.sh less    # less work for the same answer (issue 47): the CUDA variants of the warm-start,
#                                  # line-of-sight-first, stopping-rule, ordered-subsets, coarse-to-fine, slab and
#                                  # weight-build tests; fast's stages on Mc (mcfast.py, against fixed), M and 23
#                                  # planes of L by fast (goals: M <= 1 s, L <= 60 s), Mc warm-started (~9 minutes)
#   bash benchmarks/gpu.sh particles # particles, not voxels (issue 48): the particle tests' CUDA variants,
#                                  # IPR against DRT-MART's peaks on the tiny rig and on Mc (the issue's
#                                  # 512 x 512 rig), then the tracks against the truth (about 9 minutes)
#   bash benchmarks/gpu.sh short   # the correlation's CUDA tests and benchmark, M by MLOS-MART (50
#                                  # iterations), then the weight-build profile (what fits in 6 min)
#
# Each step runs under its own time limit, so one slow case cannot take the whole call; logs go
# to $OUT (or ./gpu-logs) and a short summary is printed last.
set -u
stage=${1:-tests}
out=${OUT:-gpu-logs}
mkdir -p "$out"
export PYTHONUNBUFFERED=1
summary=()

step() {  # step NAME SECONDS COMMAND...
    local name=$1 limit=$2
    shift 2
    local t0=$SECONDS
    echo "=== $name (limit ${limit} s): $*" | tee -a "$out/$stage.log"
    timeout -k 10 "$limit" "$@" >>"$out/$stage.log" 2>&1
    local rc=$?
    summary+=("$name: rc $rc, $((SECONDS - t0)) s")
    tail -n 25 "$out/$stage.log"
}

if [ "$stage" = tests ]; then
    nvidia-smi --query-gpu=name,memory.total,driver_version --format=csv,noheader | tee -a "$out/$stage.log"
    python3 -c "import warp as wp; wp.init(); print('warp', wp.__version__, wp.get_cuda_devices())" \
        >>"$out/$stage.log" 2>&1
    step pytest 330 python3 -m pytest tests -q -k "cuda or functional" -p no:cacheprovider \
        --continue-on-collection-errors --timeout 150 --junitxml "$out/pytest.xml"
    step render 60 python3 benchmarks/render.py --device cuda:0
    step correlate 90 python3 benchmarks/correlate.py --case gpu --profile
    step recon-S 60 python3 benchmarks/recon.py --case S --case S2 --case T4 --device cuda
    step live-S 60 python3 benchmarks/live.py --case S --device cuda --seconds 10
    step operator-overhead 40 python3 benchmarks/operator_overhead.py --device cuda
elif [ "$stage" = tomo ]; then
    step pytest-tomo 200 python3 -m pytest tests/unit/lfcore/test_pinhole_projector.py tests/functional/test_tomo_cli.py \
        -q -p no:cacheprovider --timeout 150 --junitxml "$out/pytest-tomo.xml"
    step recon-T 120 python3 benchmarks/recon.py --case T4 --case T6 --case T8 --device cuda
    step study-lf-vs-tomo 240 python3 -m lfpiv study lf-vs-tomo --scale quick --out "$out/studies" --device cuda \
        --overwrite
elif [ "$stage" = iter ]; then
    step pytest-unit-cuda 200 python3 -m pytest tests/unit -q -k cuda -p no:cacheprovider --timeout 100 \
        --junitxml "$out/pytest-unit.xml"
    step recon-S 60 python3 benchmarks/recon.py --case S --case S2 --device cuda
    step recon-M 150 python3 benchmarks/recon.py --case M --device cuda --no-mart --iterations 50
    step live-M-mlos 100 python3 benchmarks/live.py --case M --device cuda --seconds 15 --method mlos-mart \
        --distinct 8 --warmup-limit 60
elif [ "$stage" = live ]; then
    step live-M-mlos 120 python3 benchmarks/live.py --case M --device cuda --seconds 15 --method mlos-mart \
        --distinct 8 --warmup-limit 60
    step live-S-drt 40 python3 benchmarks/live.py --case S --device cuda --seconds 10
    step live-S-mlos 40 python3 benchmarks/live.py --case S --device cuda --seconds 10 --method mlos-mart
    step recon-L-mlos 60 python3 benchmarks/recon.py --case L --device cuda --no-drt --no-mart --iterations 20 \
        --weight-storage stored
    step pytest 240 python3 -m pytest tests -q -k "cuda or functional" -p no:cacheprovider \
        --continue-on-collection-errors --timeout 150 --junitxml "$out/pytest.xml"
elif [ "$stage" = matrixfree ]; then
    step pytest-mf-cuda 100 python3 -m pytest tests/unit/lfcore/test_matrix_free.py -q -k cuda -p no:cacheprovider \
        --timeout 90
    step recon-S-mf 45 python3 benchmarks/recon.py --case S --device cuda --projector both --no-mart
    step recon-Mc-mf 80 python3 benchmarks/recon.py --case Mc --device cuda --projector both --no-mart \
        --on-the-fly-iterations 5 --interleaved 4
    step recon-M-mf 110 python3 benchmarks/recon.py --case M --device cuda --projector matrix-free --no-mart \
        --on-the-fly-iterations 2
    step live-M-mf 90 python3 benchmarks/live.py --case M --device cuda --seconds 15 --projector matrix-free \
        --distinct 8 --warmup-limit 50
    # L's images do not fit (about 1.3 TB), so its templates are applied in every iteration: a middle sample
    # of 23 planes (6.4 M active voxels) gives the rate per voxel and iteration, to scale to L's 368 M
    step recon-L-mf-mid 100 python3 benchmarks/recon.py --case L --device cuda --slabs 1 --planes 80:103 \
        --iterations 3 --weight-storage on-the-fly
elif [ "$stage" = slabs ]; then
    step pytest-slabs-cuda 120 python3 -m pytest tests/unit/lfcore/test_slabs.py tests/unit/lfcore/test_slab_correlate.py \
        -q -k cuda -p no:cacheprovider --timeout 100
    step slabs-12M 60 python3 benchmarks/slabs.py --device cuda --pvr 0.5,0.5,2 --slabs 8
    step slabs-52M 120 python3 benchmarks/slabs.py --device cuda --pvr 0.25,0.25,2 --slabs 8
    step slabs-correlate-34M 180 python3 benchmarks/slabs.py --device cuda --correlate --shape 256,256,512 --slabs 8
elif [ "$stage" = short ]; then
    step pytest-correlate-cuda 80 python3 -m pytest tests/unit/lfcore/test_correlate.py -q -k cuda -p no:cacheprovider \
        --timeout 60
    step correlate 70 python3 benchmarks/correlate.py --case gpu --profile
    step recon-M-mlos 140 python3 benchmarks/recon.py --case M --device cuda --no-drt --no-mart --iterations 50
    step weights-Mc 80 python3 benchmarks/recon.py --case Mc --ppm 1 --device cuda --profile-weights
elif [ "$stage" = corr ]; then
    step pytest-correlate 200 python3 -m pytest tests/unit/lfcore/test_correlate.py tests/functional/test_correlate_cli.py -q \
        -p no:cacheprovider --timeout 100
    step correlate 200 python3 benchmarks/correlate.py --case gpu --profile
    step correlate-r4 100 python3 benchmarks/correlate.py --case gpu --variant direct-first50 --search-radius 4
elif [ "$stage" = monitor ]; then
    step pytest-elim-live-cuda 120 python3 -m pytest tests/unit/lfcore/test_weight_build.py tests/unit/realtime -q -k cuda \
        -p no:cacheprovider --timeout 100
    step live-M-mlos 110 python3 benchmarks/live.py --case M --device cuda --seconds 15 --method mlos-mart \
        --distinct 8 --warmup-limit 60
    step live-M-mlos-pvr4 90 python3 benchmarks/live.py --case M --device cuda --seconds 15 --method mlos-mart \
        --distinct 8 --warmup-limit 60 --pvr 4,4,20
    step live-M-mlos-pvr6 80 python3 benchmarks/live.py --case M --device cuda --seconds 15 --method mlos-mart \
        --distinct 8 --warmup-limit 60 --pvr 6,6,30
    step recon-M-mlos 100 python3 benchmarks/recon.py --case M --device cuda --no-drt --no-mart --iterations 50
elif [ "$stage" = quality ]; then
    step recon-M-400 240 python3 benchmarks/recon.py --case M --device cuda --no-mart
    step recon-Mc2-400 150 python3 benchmarks/recon.py --case Mc2 --device cuda --iterations 400
    step recon-S2-400 60 python3 benchmarks/recon.py --case S2 --device cuda --iterations 400
    step recon-Mc2-ppm1 120 python3 benchmarks/recon.py --case Mc2 --ppm 1 --device cuda
elif [ "$stage" = fly ]; then
    step pytest-fly-cuda 150 python3 -m pytest tests/unit/lfcore/test_reconstruct.py -q -k "cuda and (fly or single)" \
        -p no:cacheprovider --timeout 100
    step recon-M-stored 100 python3 benchmarks/recon.py --case M --device cuda --no-drt --no-mart --iterations 20 \
        --weight-storage stored
    step recon-M-fly 120 python3 benchmarks/recon.py --case M --device cuda --no-drt --no-mart --iterations 20 \
        --weight-storage on-the-fly
    step recon-L-mlos 300 python3 benchmarks/recon.py --case L --device cuda --no-drt --no-mart --iterations 3
elif [ "$stage" = batch ]; then
    step batch-S 60 python3 benchmarks/batch.py --case S --pairs 3 --device cuda
    step batch-M 300 python3 benchmarks/batch.py --case M --pairs 3 --device cuda
elif [ "$stage" = less ]; then
    step pytest-less 120 python3 -m pytest tests/unit/lfcore/test_warm.py tests/unit/lfcore/test_los_first.py \
        tests/unit/lfcore/test_stopping.py tests/unit/lfcore/test_subsets.py tests/unit/lfcore/test_coarse.py \
        tests/unit/lfcore/test_coarse_prune.py tests/unit/lfcore/test_slabs_fast.py tests/unit/lfcore/test_weight_build.py \
        -q -k cuda -p no:cacheprovider --timeout 100
    step fast-Mc 100 python3 benchmarks/mcfast.py --case Mc --rows "fixed|fast" --device cuda
    step fast-M 150 python3 benchmarks/recon.py --case M --device cuda --no-mart --slabs 1 --protocol fast
    step fast-L-mid 120 python3 benchmarks/recon.py --case L --device cuda --no-mart --slabs 1 --planes 80:103 \
        --protocol fast
    step warm-Mc 80 python3 benchmarks/warm.py --case Mc --pairs 3 --iterations 400 --counts 40,80 --device cuda
elif [ "$stage" = particles ]; then
    step pytest-particles 150 python3 -m pytest tests/unit/lfcore/test_ipr.py tests/unit/realtime/test_particle_route.py \
        -q -k cuda -p no:cacheprovider --timeout 120
    step particles-tiny 90 python3 benchmarks/particles.py --frames 3 --device cuda
    step particles-Mc 240 python3 benchmarks/particles.py --case Mc --frames 1 --device cuda
    step track-tiny 60 python3 benchmarks/track.py --case uniform --pairs 3
elif [ "$stage" = profile ]; then
    step pytest-correlate 150 python3 -m pytest tests/unit/lfcore/test_correlate.py tests/functional/test_correlate_cli.py -q \
        -p no:cacheprovider --timeout 100
    step correlate 90 python3 benchmarks/correlate.py --case gpu --profile
    step weights-Mc 150 python3 benchmarks/recon.py --case Mc --ppm 1 --device cuda --profile-weights
else
    step weights-Mc 100 python3 benchmarks/recon.py --case Mc --ppm 1 --device cuda --profile-weights
    step recon-M 150 python3 benchmarks/recon.py --case M --device cuda --no-mart --iterations 50
    step live-M-mlos 100 python3 benchmarks/live.py --case M --device cuda --seconds 15 --method mlos-mart
    step live-M-drt 100 python3 benchmarks/live.py --case M --device cuda --seconds 15
    step recon-L-mlos 60 python3 benchmarks/recon.py --case L --device cuda --no-drt --no-mart --iterations 20 \
        --weight-storage stored
fi
echo "=== summary ($stage)"
printf '%s\n' "${summary[@]}"
