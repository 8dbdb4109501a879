#!/usr/bin/env bash
# Independent test bench (issue #26 item 1): sweeps from ../shared/tools/usphantom.py, a B-mode model
# written apart from echosurf's simulator, run through `echosurf extract` and scored with `echosurf compare`
# against the generator's truth. Run by hand (not in CI); prints a markdown table and PASS/FAIL per target.
#
# Usage: scripts/independent_bench.sh [--data DIR] [--out DIR] [--shapes "duck hand"] [--routes "rbf voxel"]
#                                     [-- EXTRA EXTRACT ARGS...]
#   --data DIR    holds duck/ and hand/ (generated there when their files are missing);
#                 default $INDEP_DATA or target/independent
#   --out DIR     meshes, logs and compare JSON; default target/independent-bench
#   --shapes      which phantoms (default "duck hand")
#   --routes      rbf = `extract` defaults (+ EXTRA ARGS), voxel = `extract --method voxel` (default both)
#   --by-angle    also print, per phantom, where its walls are lost per band of angle to the beam (issue #26
#                 item 6): `examples/wall_by_angle.rs` on the sweep, its truth and the rbf mesh (its band,
#                 samples and crests are those of extract's defaults, whatever the EXTRA ARGS)
#   after --       extra arguments for the rbf route's `extract`, e.g. `-- --sheet iso`
# Environment: ECHOSURF (binary; default target/release/echosurf, built when missing), USPHANTOM_PYTHON (a
# python with numpy scipy scikit-image trimesh; default: a venv created in target/usphantom-venv from PyPI),
# INDEP_DATA (as --data), WALL_BY_ANGLE (the example's binary; default
# target/release/examples/wall_by_angle, built when missing).
#
# The duck's truth is truth_outer.stl + truth_inner.stl concatenated into one binary STL (compare takes one
# truth). Their normals point inward; the swept-facing score uses |cos| between the truth normal and the beam
# with `--facing either`, so it does not depend on the orientation and no flip is needed.
set -euo pipefail

root=$(cd "$(dirname "$0")/.." && pwd)
data=${INDEP_DATA:-$root/target/independent}
out=$root/target/independent-bench
shapes="duck hand"
routes="rbf voxel"
extra=()
by_angle=0
while [ $# -gt 0 ]; do
    case "$1" in
        --data) data=$2; shift 2 ;;
        --out) out=$2; shift 2 ;;
        --shapes) shapes=$2; shift 2 ;;
        --routes) routes=$2; shift 2 ;;
        --by-angle) by_angle=1; shift ;;
        --) shift; extra=("$@"); break ;;
        -h|--help) sed -n '2,24p' "$0"; exit 0 ;;
        *) echo "independent_bench.sh: unknown argument '$1' (see --help)" >&2; exit 2 ;;
    esac
done
for s in $shapes; do
    case "$s" in duck|hand) ;; *) echo "independent_bench.sh: unknown shape '$s' (duck, hand)" >&2; exit 2 ;; esac
done
for r in $routes; do
    case "$r" in rbf|voxel) ;; *) echo "independent_bench.sh: unknown route '$r' (rbf, voxel)" >&2; exit 2 ;; esac
done

echosurf=${ECHOSURF:-$root/target/release/echosurf}
if [ ! -x "$echosurf" ]; then
    (cd "$root" && cargo build --release -p echosurf-cli)
fi
generator=$root/../shared/tools/usphantom.py
wall_by_angle=${WALL_BY_ANGLE:-$root/target/release/examples/wall_by_angle}
if [ "$by_angle" -eq 1 ] && [ ! -x "$wall_by_angle" ]; then
    (cd "$root" && cargo build --release -p echosurf-bench --example wall_by_angle)
fi

python_for_generator() {
    if [ -n "${USPHANTOM_PYTHON:-}" ]; then
        echo "$USPHANTOM_PYTHON"
        return
    fi
    local venv=$root/target/usphantom-venv
    if [ ! -x "$venv/bin/python" ] || ! "$venv/bin/python" -c 'import numpy, scipy, skimage, trimesh' 2>/dev/null; then
        python3 -m venv "$venv" >&2
        "$venv/bin/pip" install --quiet numpy scipy scikit-image trimesh >&2
    fi
    echo "$venv/bin/python"
}

seed_of() { case "$1" in duck) echo 7 ;; hand) echo 11 ;; esac; }
frames_of() { case "$1" in duck) echo 90 ;; hand) echo 70 ;; esac; }
iso_of() { case "$1" in duck) echo 50 ;; hand) echo auto ;; esac; }
truths_of() { case "$1" in duck) echo "truth_outer.stl truth_inner.stl" ;; hand) echo "truth_outer.stl" ;; esac; }

# Binary STL: 80-byte header, little-endian u32 triangle count, 50 bytes per triangle.
stl_count() {
    local file=$1 n size
    n=$(od -An -t u4 -j 80 -N 4 "$file" | tr -d ' ')
    size=$(wc -c <"$file")
    if [ -z "$n" ] || [ "$size" -ne $((84 + 50 * n)) ]; then
        echo "independent_bench.sh: $file is not a binary STL ($size bytes for $n triangles)" >&2
        exit 1
    fi
    echo "$n"
}
u32_le() {
    local n=$1
    printf "\\x$(printf %02x $((n & 255)))\\x$(printf %02x $(((n >> 8) & 255)))"
    printf "\\x$(printf %02x $(((n >> 16) & 255)))\\x$(printf %02x $(((n >> 24) & 255)))"
}
merge_stl() {
    local target=$1 total=0 f tmp
    shift
    for f in "$@"; do total=$((total + $(stl_count "$f"))); done
    tmp=$target.partial
    {
        head -c 80 "$1"
        u32_le "$total"
        for f in "$@"; do tail -c +85 "$f"; done
    } >"$tmp"
    mv "$tmp" "$target"
}

json_get() { # FILE EXPR: a number from compare's JSON, with the python-free tool chain (grep/sed).
    grep -o "\"$2\":[^,}]*" "$1" | head -n 1 | sed 's/.*://'
}

mkdir -p "$out"
rows=()
verdicts=()
status=0
for shape in $shapes; do
    dir=$data/$shape
    missing=0
    for f in "$shape.mha" "${shape}_config.xml" $(truths_of "$shape"); do
        [ -f "$dir/$f" ] || missing=1
    done
    if [ "$missing" -eq 1 ]; then
        py=$(python_for_generator)
        echo "generating $shape (seed $(seed_of "$shape"), $(frames_of "$shape") frames/sweep) in $dir" >&2
        "$py" "$generator" "$dir" --shape "$shape" --seed "$(seed_of "$shape")" --frames "$(frames_of "$shape")" >&2
    fi
    truth_files=()
    for f in $(truths_of "$shape"); do truth_files+=("$dir/$f"); done
    truth=$out/${shape}_truth.stl
    merge_stl "$truth" "${truth_files[@]}"

    for route in $routes; do
        mesh=$out/${shape}_$route.ply
        log=$out/${shape}_$route.log
        args=("$dir/$shape.mha" --calibration "$dir/${shape}_config.xml" --iso "$(iso_of "$shape")" --out "$mesh")
        if [ "$route" = voxel ]; then
            args+=(--method voxel)
        else
            args+=("${extra[@]}")
        fi
        rm -f "$mesh"
        start=$(date +%s.%N)
        if ! "$echosurf" extract "${args[@]}" >"$log" 2>&1; then
            echo "independent_bench.sh: extract failed for $shape/$route, see $log" >&2
            rows+=("| $shape | $route | extract failed | | | | | | | |")
            status=1
            continue
        fi
        end=$(date +%s.%N)
        seconds=$(awk -v a="$start" -v b="$end" 'BEGIN { printf "%.1f", b - a }')
        json=$out/${shape}_$route.json
        "$echosurf" compare "$mesh" "$truth" --sequence "$dir/$shape.mha" --calibration "$dir/${shape}_config.xml" \
            --facing either --facing-deg 60 --json >"$json"
        mean=$(json_get "$json" mean_mm)
        p95=$(json_get "$json" p95_mm)
        # swept_facing's completeness is the second completeness_1mm in the object (after the whole truth's).
        coverage=$(grep -o '"completeness_1mm":[^,}]*' "$json" | sed -n 2p | sed 's/.*://')
        pieces=$(json_get "$json" components)
        share=$(json_get "$json" mesh_largest_piece_area_share)
        # Pieces that run from one of the truth's walls (components) onto another (issue item 5: none).
        joining=$(json_get "$json" pieces_on_several_walls)
        max_pieces=$([ "$shape" = duck ] && echo 2 || echo 1)
        row=$(awk -v s="$shape" -v r="$route" -v m="$mean" -v p="$p95" -v c="$coverage" -v n="$pieces" \
            -v a="$share" -v t="$seconds" -v mp="$max_pieces" -v j="$joining" 'BEGIN {
                ok = (m <= 0.30) && (p <= 0.60) && (c >= 0.98) && (n <= mp) && (s != "duck" || t <= 4.0)
                printf "| %s | %s | %.3f %s | %.3f %s | %.3f %s | %d %s | %.2f | %d | %.1f %s | %s |",
                    s, r, m, (m <= 0.30 ? "PASS" : "FAIL"), p, (p <= 0.60 ? "PASS" : "FAIL"),
                    c, (c >= 0.98 ? "PASS" : "FAIL"), n, (n <= mp ? "PASS" : "FAIL"), a, j,
                    t, (s == "duck" ? (t <= 4.0 ? "PASS" : "FAIL") : "-"), (ok ? "PASS" : "FAIL")
            }')
        rows+=("$row")
        case "$row" in *"| FAIL |") verdicts+=("$shape/$route FAIL") ;; *) verdicts+=("$shape/$route PASS") ;; esac
    done
done

echo
echo "Independent bench: $("$echosurf" --version), extra rbf args: ${extra[*]:-(none)}"
# Times are wall clock: read them against the machine's load.
echo "load average at the end: $(cut -d' ' -f1-3 /proc/loadavg 2>/dev/null || echo unknown), $(nproc) cores"
echo
echo "| phantom | route | mean mm (<= 0.30) | p95 mm (<= 0.60) | swept facing 60 deg within 1 mm (>= 0.98) | pieces (duck <= 2, hand 1) | largest piece share | pieces on several walls | extract s (duck <= 4) | all |"
echo "|---|---|---|---|---|---|---|---|---|---|"
for r in "${rows[@]}"; do echo "$r"; done
echo
for v in "${verdicts[@]}"; do echo "$v"; done
if [ "$by_angle" -eq 1 ]; then
    for shape in $shapes; do
        mesh=$out/${shape}_rbf.ply
        [ -f "$mesh" ] || continue
        dir=$data/$shape
        truth_files=()
        for f in $(truths_of "$shape"); do truth_files+=("$dir/$f"); done
        echo
        echo "$shape, per band of angle between wall and beam (shares of each frame's cut through the truth):"
        echo
        if ! "$wall_by_angle" "$dir/$shape.mha" "$dir/${shape}_config.xml" "${truth_files[@]}" --mesh "$mesh"; then
            echo "independent_bench.sh: wall_by_angle failed for $shape" >&2
            status=1
        fi
    done
fi
exit $status
