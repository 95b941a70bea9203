# The two README commands: `make demo` and `make test`. Only Python 3.11 (and make) are needed.
PYTHON ?= python3.11
VENV := .venv
BIN := $(VENV)/bin
STAMP := $(VENV)/.installed

.PHONY: setup demo test browser test-cpu-paths fuzz readme-figure bench bench-detect eval-framings eval-groups eval-sessions eval-video bench-faces prior ae-weights eval-ae eval-sunsky eval-fit-faces eval-real eval-real-heldout eval-real-ablations eval-real-geometry eval-real-search hdri-import sun-table clean

$(STAMP): pyproject.toml
	$(PYTHON) -m venv $(VENV)
	@# -qq: pip shows errors only (a machine's pip configuration may name package locations that
	@# do not exist, and pip warns about each for every package); setuptools reports that it
	@# implements the editable install with a meta path finder (plugins/ and schemas/ map into
	@# packages): expected here, so not shown
	$(BIN)/python -m pip install -qq --upgrade pip
	PYTHONWARNINGS="ignore:Editable installation" $(BIN)/python -m pip install -qq -e '.[test]'
	touch $(STAMP)

setup: $(STAMP)

demo: $(STAMP)
	$(BIN)/f2l demo --out demo_out

# The report's browser test needs Chromium: Debian's package, installed where the machine allows
# (root and apt); elsewhere that one test skips and says why.
# Two worker processes (pytest-xdist); a test file stays on one worker, so a module's fixtures are
# built once. ~13 min on 2 cores against ~20 in one process; TEST_WORKERS=0 runs it in one process.
TEST_WORKERS ?= 2
test: $(STAMP) browser
	$(BIN)/python -m pytest -q -n $(TEST_WORKERS) --dist loadfile

browser:
	@command -v chromium >/dev/null 2>&1 || { [ "$$(id -u)" = 0 ] && command -v apt-get >/dev/null 2>&1 && \
		{ DEBIAN_FRONTEND=noninteractive apt-get install -y -qq chromium >/dev/null 2>&1 || \
		  { apt-get update -qq >/dev/null 2>&1 && DEBIAN_FRONTEND=noninteractive apt-get install -y -qq chromium >/dev/null 2>&1; }; }; } || \
		echo "chromium is not installed (needs root and apt): the report's browser test will skip"

# The suite once per CPU code path (OpenBLAS kernel, ATen SIMD level, MKL instruction set), one
# machine, ~2 min each; table in build/cpu_paths.md (docs/numerics.md). Not part of `make test`.
test-cpu-paths: $(STAMP)
	$(BIN)/python tests/cpu_paths.py --report build/cpu_paths.md

bench: $(STAMP)
	$(BIN)/f2l dev bench --faces 1

# Every reader of outside input fed 2,000 mutated files each, and every batch command 100-200, under a 2 GB address-space limit
# (tests/fuzzing.py; each target in its own process; `make test` runs 60 per reader): ~8 min on 2 cores. Replay a failure with
# `$(BIN)/python tests/fuzzing.py --target T --first CASE --cases 1 --seed 1`.
fuzz: $(STAMP)
	$(BIN)/python tests/fuzzing.py --cases 2000 --seed 1 --memory-gb 2

# The README's picture (docs/example.png): a real photo, its estimated probe, an object lit by it (~10 s)
readme-figure: $(STAMP)
	$(BIN)/python -m f2l.dev.readme_figure

# Face detection on real photographs framed wide (docs/experiments/face_detection.md): recall by face
# width, false detections per 100 face-free photos, time by photo size (~1 min on 2 cores)
bench-detect: $(STAMP)
	$(BIN)/f2l dev bench-detect

bench-faces: $(STAMP)
	$(BIN)/f2l dev bench-faces --faces 6

# Real framings, path-traced (f2l/render/framing.py): 30 half-body, 30 full-body and 40 group photos (2-5
# people; ~200 faces) at 1280 px and 16 spp; detection recall by face width and framing (bench-detect
# --rendered), then fit, estimate (sunsky) and the accuracy-against-face-size table (eval-framings,
# f2l/evaluation/face_width.py; docs/results/framings.md), with each photo's faces sharing a light (the default) and
# each face alone (--joint none, in $(EVAL_FRAMINGS)/alone). ~60 min on 2 cores; resumable.
EVAL_FRAMINGS := build/eval_framings
eval-framings: $(STAMP)
	$(BIN)/f2l eval render-faces --framing half --out $(EVAL_FRAMINGS)/half --n 30 --seed 0 --image-px 1280 --spp 16 --json
	$(BIN)/f2l eval render-faces --framing full --out $(EVAL_FRAMINGS)/full --n 30 --seed 0 --image-px 1280 --spp 16 --json
	$(BIN)/f2l eval render-faces --framing group --out $(EVAL_FRAMINGS)/group --n 40 --seed 0 --image-px 1280 --spp 16 --json
	$(BIN)/f2l dev bench-detect --rendered $(EVAL_FRAMINGS)/half --rendered $(EVAL_FRAMINGS)/full \
		--rendered $(EVAL_FRAMINGS)/group
	$(BIN)/f2l fit-faces $(EVAL_FRAMINGS)/half/photos $(EVAL_FRAMINGS)/full/photos $(EVAL_FRAMINGS)/group/photos \
		--out $(EVAL_FRAMINGS)/fitted --json
	$(BIN)/f2l estimate $(EVAL_FRAMINGS)/fitted -m sunsky --out $(EVAL_FRAMINGS)/est --json
	$(BIN)/f2l eval framings $(EVAL_FRAMINGS)/half $(EVAL_FRAMINGS)/full $(EVAL_FRAMINGS)/group \
		--fitted $(EVAL_FRAMINGS)/fitted --est $(EVAL_FRAMINGS)/est --out $(EVAL_FRAMINGS)
	$(BIN)/f2l estimate $(EVAL_FRAMINGS)/fitted -m sunsky --joint none --out $(EVAL_FRAMINGS)/est_alone --json
	$(BIN)/f2l eval framings $(EVAL_FRAMINGS)/half $(EVAL_FRAMINGS)/full $(EVAL_FRAMINGS)/group \
		--fitted $(EVAL_FRAMINGS)/fitted --est $(EVAL_FRAMINGS)/est_alone --out $(EVAL_FRAMINGS)/alone

# One light for many faces (f2l.estimate.joint; docs/experiments/joint_estimate.md): 80 path-traced group
# photos (2-5 people under one light) on seed 0 to tune on and 80 on seed 1 to report on (40 each until
# 2026-11-28: one photo moved a set's mean by 3 degrees), fitted, then each photo's first 1, 2, 3 and 5 faces
# estimated one at a time and jointly (sunsky) and scored against the truth; tables in
# build/eval_groups/{tune,report}/groups.md. About 100 min on 2 cores; the renders are resumable.
EVAL_GROUPS := build/eval_groups
eval-groups: $(STAMP)
	$(BIN)/f2l eval render-faces --framing group --out $(EVAL_GROUPS)/render_tune --n 80 --seed 0 --image-px 1280 --spp 16 --json
	$(BIN)/f2l eval render-faces --framing group --out $(EVAL_GROUPS)/render_report --n 80 --seed 1 --image-px 1280 --spp 16 --json
	$(BIN)/f2l fit-faces $(EVAL_GROUPS)/render_tune/photos --out $(EVAL_GROUPS)/fitted_tune --json
	$(BIN)/f2l fit-faces $(EVAL_GROUPS)/render_report/photos --out $(EVAL_GROUPS)/fitted_report --json
	$(BIN)/f2l eval groups $(EVAL_GROUPS)/render_tune --fitted $(EVAL_GROUPS)/fitted_tune --out $(EVAL_GROUPS)/tune
	$(BIN)/f2l eval groups $(EVAL_GROUPS)/render_report --fitted $(EVAL_GROUPS)/fitted_report --out $(EVAL_GROUPS)/report

# Sessions (issue 42): 12 sessions of 3 path-traced portraits, different people under one light, each
# camera turned within ±90° (f2l eval render-faces --session-size 3); each face estimated alone and the
# session jointly in the first photo's frame (sunsky). Table in build/eval_sessions/eval/sessions.md;
# build/eval_sessions/tagged holds the records with meta session and camera_yaw_deg (for
# `f2l estimate --joint session`). About 7 min on 2 cores; the renders are resumable.
EVAL_SESSIONS := build/eval_sessions
eval-sessions: $(STAMP)
	$(BIN)/f2l eval render-faces --out $(EVAL_SESSIONS)/render --n 36 --seed 0 --session-size 3 --image-px 320 --spp 32 --json
	$(BIN)/f2l fit-faces $(EVAL_SESSIONS)/render/photos --out $(EVAL_SESSIONS)/fitted --json
	$(BIN)/f2l eval sessions $(EVAL_SESSIONS)/render --fitted $(EVAL_SESSIONS)/fitted --out $(EVAL_SESSIONS)/eval --tag $(EVAL_SESSIONS)/tagged

# Light from video (f2l video; f2l.video): path-traced clips of a head turning and nodding, 48
# frames at 1280x720, static light, a cloud over the sun or a cut (render-faces --sequence);
# seed 0 tunes, seed 1 reports. Per clip: Sun-ang against each frame alone as a photo, jitter,
# settling after a change, the 5.1 metrics and frames/s; then frames/s on 10-second clips (each
# static clip played back and forth 5 times). About 25 min on 2 cores; the renders are resumable.
EVAL_VIDEO := build/eval_video
eval-video: $(STAMP)
	$(BIN)/f2l eval render-faces --sequence --clip-kind mixed --n 6 --frames 48 --seed 0 --out $(EVAL_VIDEO)/s0 --json
	$(BIN)/f2l eval render-faces --sequence --clip-kind mixed --n 6 --frames 48 --seed 1 --out $(EVAL_VIDEO)/s1 --json
	$(BIN)/f2l eval render-faces --sequence --clip-kind mixed --n 6 --frames 48 --seed 2 --out $(EVAL_VIDEO)/s2 --json
	$(BIN)/f2l eval render-faces --sequence --clip-kind mixed --n 6 --frames 48 --seed 3 --out $(EVAL_VIDEO)/s3 --json
	$(BIN)/f2l eval video $(EVAL_VIDEO)/s0 $(EVAL_VIDEO)/s1 $(EVAL_VIDEO)/s2 $(EVAL_VIDEO)/s3 --out $(EVAL_VIDEO)/eval
	$(BIN)/f2l dev bench-video $(EVAL_VIDEO)/s0/clips/clip-s0-00000-static.mp4 $(EVAL_VIDEO)/s1/clips/clip-s1-00000-static.mp4 --repeat 5

# Rebuild the shipped Sun+Sky GMM prior from the project's own sky corpus (~15 min on 2 cores).
prior: $(STAMP)
	$(BIN)/f2l prior sky-corpus --out build/sky_corpus --n 200 --seed 0 --json
	$(BIN)/f2l prior build build/sky_corpus --model sunsky --components 6 --seed 0 \
		--out plugins/f2l_builtin_models/data/sunsky_prior.json --json

# A face in an occluder's shadow (issue 42; docs/experiments/joint_estimate.md): 200 path-traced group photos
# on seed 11 with --shade-one (a dark board puts one person's face in its shadow where the sky is clear, the
# sun lights that face and the board can stay off the others and off the faces: 38 of the 200), fitted, then
# each shaded photo estimated jointly with the check on, without the shaded face and with the check off
# (sunsky); tables in build/eval_shade/report/shade.md. Seed 11 tunes the rules, seed 12 (55 shaded photos
# of 200) reports: build/eval_shade_s12/report/shade.md. About 1.5 h a seed on 2 cores; the renders are resumable.
EVAL_SHADE := build/eval_shade
.PHONY: eval-shade
eval-shade: $(STAMP)
	$(BIN)/f2l eval render-faces --framing group --shade-one --out $(EVAL_SHADE)/render --n 200 --seed 11 --image-px 1280 --spp 8 --json
	$(BIN)/f2l fit-faces $(EVAL_SHADE)/render/photos --out $(EVAL_SHADE)/fitted --json
	$(BIN)/f2l eval shade $(EVAL_SHADE)/render --fitted $(EVAL_SHADE)/fitted --out $(EVAL_SHADE)/report
	$(BIN)/f2l eval render-faces --framing group --shade-one --out $(EVAL_SHADE)_s12/render --n 200 --seed 12 --image-px 1280 --spp 8 --json
	$(BIN)/f2l fit-faces $(EVAL_SHADE)_s12/render/photos --out $(EVAL_SHADE)_s12/fitted --json
	$(BIN)/f2l eval shade $(EVAL_SHADE)_s12/render --fitted $(EVAL_SHADE)_s12/fitted --out $(EVAL_SHADE)_s12/report

# Rebuild the shipped sky-autoencoder weights (+ latent prior, model card, loss curve) from the
# project's own sky corpus (docs/ae.md): 16.5 min on 2 cores; bit-identical tensors on the machine that
# trained them, the same held-out metrics elsewhere (docs/numerics.md). Resumable.
ae-weights: $(STAMP)
	$(BIN)/f2l ae corpus --out build/ae_corpus --n-train 4000 --n-heldout 150 --seed 0 --json
	$(BIN)/f2l ae train build/ae_corpus/train --heldout build/ae_corpus/heldout --work-dir build/ae_train \
		--epochs 5 --batch-size 16 --seed 0 --out plugins/f2l_builtin_models/data/ae_sky.npz

# Sky autoencoder against the other built-in models (docs/results/ae.md): paper Table 1 —
# each model fitted to the 150 held-out skies of the `make ae-weights` corpus (regenerated alone,
# identical; ~45 min on 2 cores) — then the same models estimated from 24 synthetic faces (~4 min).
# The synthetic faces are Lambertian: read them so (--skin-gloss 0 --skin-reflection 0; the defaults are for real skin), with the sharp
# sun as fitted (--set sun_spread=0: the default spreads it over a cone calibrated on path-traced faces).
EVAL_AE := build/eval_ae
eval-ae: $(STAMP)
	$(BIN)/f2l ae corpus --out $(EVAL_AE)/corpus --n-train 4000 --n-heldout 150 --seed 0 --split heldout --json
	for m in sh9 sh25 sunsky ae; do \
		$(BIN)/f2l eval fit-probe $(EVAL_AE)/corpus/heldout --model $$m --out $(EVAL_AE)/table1/$$m || exit 1; \
	done
	$(BIN)/f2l eval synth --out $(EVAL_AE)/faces --n 24 --seed 11 --lambertian --json
	$(BIN)/f2l estimate $(EVAL_AE)/faces -m sh9 -m sh25 -m sunsky -m ae --skin-gloss 0 --skin-reflection 0 --set sun_spread=0 --out $(EVAL_AE)/est --json
	$(BIN)/f2l evaluate $(EVAL_AE)/est

# Sun+Sky acceptance harness: median Sun-ang / Sun-dω MAE on 24 sunny faces (sun 10-70° high, all
# azimuths, noisy 8-bit photos) and the sun energy share on 10 overcast faces, SH25 for reference.
# f2l's own renders are Lambertian: read them so (--skin-gloss 0 --skin-reflection 0; the defaults are for real skin).
EVAL_SUNSKY := build/eval_sunsky
eval-sunsky: $(STAMP)
	$(BIN)/f2l eval synth --out $(EVAL_SUNSKY)/sunny --n 24 --seed 101 --overcast-fraction 0 --lambertian \
		--sun-elevation-deg 10:70 --capture --json
	$(BIN)/f2l eval synth --out $(EVAL_SUNSKY)/overcast --n 10 --seed 102 --overcast-fraction 1 --lambertian --json
	$(BIN)/f2l estimate $(EVAL_SUNSKY)/sunny -m sh25 -m sunsky --no-sun-prior --skin-gloss 0 --skin-reflection 0 --set sun_spread=0 --out $(EVAL_SUNSKY)/est_sunny --json
	$(BIN)/f2l estimate $(EVAL_SUNSKY)/sunny -m sunsky --skin-gloss 0 --skin-reflection 0 --set sun_spread=0 --out $(EVAL_SUNSKY)/est_sunny_exif --json
	$(BIN)/f2l estimate $(EVAL_SUNSKY)/overcast -m sh25 -m sunsky --skin-gloss 0 --skin-reflection 0 --set sun_spread=0 --out $(EVAL_SUNSKY)/est_overcast --json
	$(BIN)/f2l evaluate $(EVAL_SUNSKY)/est_sunny
	$(BIN)/f2l evaluate $(EVAL_SUNSKY)/est_sunny_exif
	$(BIN)/f2l evaluate $(EVAL_SUNSKY)/est_overcast

# Face fitting end to end: synthetic photos (painted features, 256 px, EXIF focal length) under
# known sunny skies -> f2l fit-faces -> normal error against the true mesh -> sunsky estimates from
# the fitted geometry and from its true-geometry twin (same pixels and observations), side by side.
# The photos are Lambertian: read them so (--skin-gloss 0 --skin-reflection 0, the sharp sun).
EVAL_FIT := build/eval_fit_faces
eval-fit-faces: $(STAMP)
	$(BIN)/f2l eval synth --out $(EVAL_FIT)/truth --n 30 --seed 301 --image-size 256 --features --lambertian \
		--overcast-fraction 0 --sun-elevation-deg 10:70 --json
	$(BIN)/f2l fit-faces $(EVAL_FIT)/truth/photos --out $(EVAL_FIT)/fitted \
		--gt-probes $(EVAL_FIT)/truth/probes --json
	$(BIN)/f2l eval compare-geometry $(EVAL_FIT)/fitted --truth $(EVAL_FIT)/truth --twin-out $(EVAL_FIT)/true_geometry
	$(BIN)/f2l estimate $(EVAL_FIT)/fitted -m sunsky --no-sun-prior --skin-gloss 0 --skin-reflection 0 --set sun_spread=0 --out $(EVAL_FIT)/est_fitted --json
	$(BIN)/f2l estimate $(EVAL_FIT)/true_geometry -m sunsky --no-sun-prior --skin-gloss 0 --skin-reflection 0 --set sun_spread=0 --out $(EVAL_FIT)/est_true_geometry --json
	$(BIN)/f2l evaluate $(EVAL_FIT)/est_fitted
	$(BIN)/f2l evaluate $(EVAL_FIT)/est_true_geometry

# Accuracy on faces f2l did not render (README "Accuracy"; all tables: docs/results/eval_real.md): EVAL_REAL_N path-traced cases
# (Mitsuba 3, Anny heads, real CC0 HDR maps and Hosek-Wilkie skies; ~10-13 s each on 2 cores: 22-28 min
# for 128, 30-37 min in all), fitted and estimated with defaults, every built-in model, on fitted and
# on the renderer's true geometry, scored with the baselines and the diagnostics; even cases tune,
# odd cases report (build/eval_real/eval_real.md), with sunsky and ae also fitted to each true probe
# (their families' oracles; 1.2 + 2.4 s a case, 9 min the first time, then cached in build/eval_real/truth_fits).
# 128 rather than 64: on 32 cases a part, single
# chaotic cases moved a part's mean Sun-ang by ~2 deg, more than most changes tried.
EVAL_REAL := build/eval_real
EVAL_REAL_N ?= 128
MODELS := -m sh9 -m sh25 -m sunsky -m ae
FIT_TRUTH := --fit-truth sunsky --fit-truth ae
eval-real: $(STAMP)
	$(BIN)/f2l eval render-faces --out $(EVAL_REAL)/pbr --n $(EVAL_REAL_N) --seed 0 --json
	$(BIN)/f2l fit-faces $(EVAL_REAL)/pbr/photos --out $(EVAL_REAL)/fitted --gt-probes $(EVAL_REAL)/pbr/probes --json
	$(BIN)/f2l eval twin-geometry $(EVAL_REAL)/fitted --render $(EVAL_REAL)/pbr --out $(EVAL_REAL)/true_geometry --json
	$(BIN)/f2l estimate $(EVAL_REAL)/fitted $(MODELS) --out $(EVAL_REAL)/est --json
	$(BIN)/f2l estimate $(EVAL_REAL)/true_geometry $(MODELS) --out $(EVAL_REAL)/est_true_geometry --json
	$(BIN)/f2l eval real $(EVAL_REAL)/pbr --est $(EVAL_REAL)/est --est "true geometry=$(EVAL_REAL)/est_true_geometry" \
		--out $(EVAL_REAL) $(FIT_TRUTH)

# On maps no default was chosen on (docs/results/eval_real.md "On maps held out from tuning"): EVAL_HELDOUT_N cases
# under the package's three other outdoor maps (city, sunrise, sunset; f2l.render.hdri.HELD_OUT_MAPS),
# rendered, fitted and estimated like eval-real; every case reports (about 20 min on 2 cores:
# rendering 12 min, fit, estimate and scoring 7 min).
EVAL_HELDOUT := build/eval_real_heldout
EVAL_HELDOUT_N ?= 64
eval-real-heldout: $(STAMP)
	$(BIN)/f2l eval render-faces --out $(EVAL_HELDOUT)/pbr --n $(EVAL_HELDOUT_N) --seed 1 --sunsky-fraction 0 --maps held-out --json
	$(BIN)/f2l fit-faces $(EVAL_HELDOUT)/pbr/photos --out $(EVAL_HELDOUT)/fitted --gt-probes $(EVAL_HELDOUT)/pbr/probes --json
	$(BIN)/f2l eval twin-geometry $(EVAL_HELDOUT)/fitted --render $(EVAL_HELDOUT)/pbr --out $(EVAL_HELDOUT)/true_geometry --json
	$(BIN)/f2l estimate $(EVAL_HELDOUT)/fitted $(MODELS) --out $(EVAL_HELDOUT)/est --json
	$(BIN)/f2l estimate $(EVAL_HELDOUT)/true_geometry $(MODELS) --out $(EVAL_HELDOUT)/est_true_geometry --json
	$(BIN)/f2l eval real $(EVAL_HELDOUT)/pbr --est $(EVAL_HELDOUT)/est --est "true geometry=$(EVAL_HELDOUT)/est_true_geometry" \
		--out $(EVAL_HELDOUT) --held-out $(FIT_TRUTH)

# The face fit's share split into normals and occluders (docs/results/eval_real.md "The face fit's share"): sunsky
# and ae on the same pixels with normals and visibility from the fitted mesh, the true body or
# neither, and on an ideal photo (f2l's own render of the truth on the true mesh, with and without
# the skin's gloss); table in
# build/eval_real/geometry_share.md. Needs `make eval-real` first (31 min on 2 cores).
eval-real-geometry: $(STAMP)
	$(BIN)/f2l eval geometry $(EVAL_REAL) -m sunsky -m ae

# The search's share of the sun error, or the objective's (docs/results/eval_real.md "Does the photo prefer the
# truth?"): sunsky on every clear face, on the fitted mesh, the true one and an ideal photo (f2l's
# own render of the truth on the true mesh), from its own starts and from a start at the true sun
# (with and without the light prior), the elevation profile off; table in
# build/eval_real/search_share.md. Needs `make eval-real` first (12 min on 2 cores).
eval-real-search: $(STAMP)
	$(BIN)/f2l eval search $(EVAL_REAL) -m sunsky

# Ablations (docs/results/eval_real.md "Where the error comes from"): the first EVAL_ABL_N cases of eval-real
# re-rendered with one thing taken away each (same people, poses, cameras and skies), then the same
# fit + estimate + scoring; table in build/eval_real/ablations.md. Needs `make eval-real` first.
EVAL_ABL_N ?= 32
ABLATIONS := no-specular:--no-specular direct-only:--max-depth=2 canonical-head:--head=canonical no-clipping:--no-clipping
eval-real-ablations: $(STAMP)
	for pair in $(ABLATIONS); do \
		name=$${pair%%:*}; flag=$${pair#*:}; dir=$(EVAL_REAL)/ablations/$$name; \
		$(BIN)/f2l eval render-faces --out $$dir/pbr --n $(EVAL_ABL_N) --seed 0 $$flag --json || exit 1; \
		$(BIN)/f2l fit-faces $$dir/pbr/photos --out $$dir/fitted --gt-probes $$dir/pbr/probes --json || exit 1; \
		$(BIN)/f2l estimate $$dir/fitted $(MODELS) --out $$dir/est --json || exit 1; \
		$(BIN)/f2l eval real $$dir/pbr --est $$dir/est --out $$dir > /dev/null || exit 1; \
	done
	$(BIN)/f2l eval ablations $(EVAL_REAL) --n $(EVAL_ABL_N)

# Re-create the shipped outdoor HDR maps (f2l/render/data/hdri) from the npm package.
hdri-import: $(STAMP)
	mkdir -p build/hdri && cd build/hdri && npm pack --silent @pmndrs/assets@1.7.0
	$(BIN)/python -c "from f2l.render.hdri import import_pmndrs; import_pmndrs('build/hdri/pmndrs-assets-1.7.0.tgz', 'f2l/render/data/hdri')"

# Re-create the shipped Hosek-Wilkie sun/sky table of `make-probes --restore-sun` (needs f2l[render]).
sun-table: $(STAMP)
	$(BIN)/python -m f2l.render.sun_table

clean:
	rm -rf $(VENV) demo_out
