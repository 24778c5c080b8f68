#!/usr/bin/env bash
# The documentation's gallery (docs/gallery.md): the paper's five experiments run in full on
# the simulated paper's bench, their figures, and the Zernike fit's, into docs/img/gallery/.
#
#   bash tools/make_gallery.sh [OUT]      # OUT: where the recordings go (default recordings/gallery)
#
# 261 trials: about 30-50 minutes with two workers on a 2-core machine. The figures' numbers are the same
# on every run and machine (the simulated rig's latency is declared); their look depends on
# matplotlib's version only.
set -euo pipefail
cd "$(dirname "$0")/.."
out=${1:-recordings/gallery}
magrun=${MAGRUN:-.venv/bin/magrun}
for protocol in prediction rate noise rate_under_noise spine; do
    "$magrun" run "protocols/$protocol.yaml" --jobs 2 --out "$out" --overwrite
done
"$magrun" figures "$out" --out "$out/figures"
mkdir -p docs/img/gallery
for name in zernike prediction rate noise rate_under_noise spine; do
    cp "$out/figures/$name.png" "docs/img/gallery/$name.png"
done
cp "$out/figures/report.md" "$out/figures/results.csv" "$out/"
echo "docs/img/gallery/: $(ls docs/img/gallery | tr '\n' ' ')"
