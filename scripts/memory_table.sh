#!/usr/bin/env bash
# Memory estimate against measured peak for every command that takes --memory-budget, on the real
# PLUS sweeps, the independent duck and the demo's duck (docs/decisions/0028-memory-budget-estimates.md).
# Run by hand from the workspace root (not in CI; it takes a few minutes):
#   scripts/memory_table.sh [BINARY] [SCRATCH_DIR]
# Each run prints its estimate (the largest figure a --memory-budget check compared) and its peak
# resident memory through `--memory-report`; the table row is command, input, estimate, peak, ratio.
set -euo pipefail

B=${1:-target/release/echosurf}
W=${2:-$(mktemp -d)}
B=$(realpath "$B")
R=$(realpath ../shared/data/real)
IND=${INDEP_DIR:-/work/indep}
mkdir -p "$W"
cd "$W"

row() { # row COMMAND_LABEL INPUT_LABEL ARGS...
    local label=$1 input=$2
    shift 2
    local line
    line=$("$B" "$@" --memory-report 2>&1 >/dev/null | grep '^memory:' | tail -1)
    local est peak ratio
    est=$(sed -E 's/.*estimate ([0-9.]+) MB.*/\1/' <<<"$line")
    peak=$(sed -E 's/.*peak resident ([0-9.]+) MB.*/\1/' <<<"$line")
    ratio=$(sed -E 's/.*peak \/ estimate ([0-9.]+)\).*/\1/' <<<"$line")
    printf '| `%s` | %s | %s MB | %s MB | %s |\n' "$label" "$input" "$est" "$peak" "$ratio"
}

iso_of() { # the automatic iso-level an extract report chose
    tr -d ' \n' <"$1" | sed -E 's/.*"iso_levels":\[([0-9.eE+-]+).*/\1/'
}

"$B" demo --out demo >/dev/null 2>&1

declare -A SEQ CFG
SEQ[spine]=$R/SpinePhantomFreehand.igs.mha
CFG[spine]=$R/PlusDeviceSet_VolumeReconstructionOnly_SpinePhantom_NN_MEAN.xml
SEQ[nwire]=$R/NwirePhantomFreehand.igs.mha
CFG[nwire]=$R/PlusDeviceSet_NwirePhantomFreehand_vtkVolumeReconstructorTest2.xml
SEQ[duck]=$IND/duck/duck.mha
CFG[duck]=$IND/duck/duck_config.xml
SEQ[demo]=demo/duck.mha
CFG[demo]=demo/duck_config.xml
declare -A NAME=([spine]="Spine sweep (NN_MEAN)" [nwire]="N-wire sweep" [duck]="independent duck" [demo]="demo duck")

echo "| command | input | estimate | peak resident | peak / estimate |"
echo "|---|---|---:|---:|---:|"
for k in spine nwire duck demo; do
    # The model and the samples have no flag: they are outputs of the option file.
    printf '[outputs]\nmodel = "%s"\nsamples = "%s"\n' "$k.esrbf" "${k}_samples.ply" > "${k}_outputs.toml"
    row "extract" "${NAME[$k]}" extract "${SEQ[$k]}" --calibration "${CFG[$k]}" --out "$k.ply" \
        --config "${k}_outputs.toml" --report "$k.json"
done
for k in spine nwire duck demo; do
    row "extract --method voxel" "${NAME[$k]}" extract "${SEQ[$k]}" --calibration "${CFG[$k]}" \
        --method voxel --out "${k}_voxel.ply"
done
for k in spine nwire duck demo; do
    row "reconstruct" "${NAME[$k]}" reconstruct "${SEQ[$k]}" --calibration "${CFG[$k]}" --out "$k.mha"
done
for k in spine nwire duck demo; do
    row "fit" "${NAME[$k]} samples" fit "${k}_samples.ply" --out "${k}_refit.esrbf"
done
for k in spine nwire duck demo; do
    row "surface" "${NAME[$k]} model" surface "$k.esrbf" --iso "$(iso_of "$k.json")" \
        --out "${k}_surface.ply"
done
row "compare" "Spine mesh vs itself" compare spine.ply spine.ply
row "compare" "independent duck mesh vs truth_outer.stl" compare duck.ply "$IND/duck/truth_outer.stl"
row "compare" "demo mesh vs its truth" compare demo.ply demo/truth.ply
row "compare" "duck truth_outer.stl vs truth_inner.stl" compare "$IND/duck/truth_outer.stl" \
    "$IND/duck/truth_inner.stl"
row "compare --samples-per-mm2 200 --max-samples 5000000" "same" compare \
    "$IND/duck/truth_outer.stl" "$IND/duck/truth_inner.stl" --samples-per-mm2 200 \
    --max-samples 5000000
