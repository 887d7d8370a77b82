# Two set-up commands for a fresh machine: `make demo` and `make test`.
# Both create .venv, install torch's CPU build first (a bare `torch` would pull
# a multi-GB CUDA build), then the project in editable mode.

PYTHON ?= python3
VENV   ?= .venv
PY     := $(VENV)/bin/python
RELIGHT := $(VENV)/bin/relight
STAMP  := $(VENV)/.installed-stamp

.PHONY: install demo example test test-fast man benchmarks study clean

$(STAMP): pyproject.toml
	test -x $(PY) || $(PYTHON) -m venv $(VENV)
	$(PY) -m pip install -q --upgrade pip
	$(PY) -m pip install -q torch==2.13.0
	$(PY) -m pip install -q -e '.[test]'
	# an editable install skips pyproject's data-files: put the man pages where `man` looks
	# for this venv (PREFIX/share/man, found from PATH); a plain `pip install .` installs them itself
	mkdir -p $(VENV)/share/man/man1 && cp man/*.1 $(VENV)/share/man/man1/
	touch $(STAMP)

install: $(STAMP)

# The main job on built-in data; results under demo/.  Steps that use the real
# data in ../shared/data run only when it is present.
SHARED := ../shared/data
# The real donut, fitted to 15 cm, laid flat (its thin axis is the file's z) and put on the floor.
DONUT := $(SHARED)/gaussians/donut-fused.ply:fit=0.15;rotate-x=-90;on-floor;translate=0.22,0,0.2
# The real robot figure (SH degree 2), captured upside down: turned over, 25 cm tall, on the floor.
ROBOT := $(SHARED)/gaussians/playbot-lod3.ply:fit=0.25;rotate-x=180;on-floor;translate=-0.25,0,0.1
demo: install
	mkdir -p demo
	# environment maps: convert, resample, inspect
	$(RELIGHT) envmap builtin:sky --to latlong --size 32x16 -o demo/sky_32x16.exr --preview demo/sky.png
	$(RELIGHT) envmap builtin:studio --to cube --size 64 -o demo/studio_cube.exr --preview demo/studio_cube.png
	$(RELIGHT) envmap demo/studio_cube.exr --info -o demo/studio_info.json
	# the default hand (built-in model, fist pose) and a preview
	$(RELIGHT) fit-geometry --pose fist -o demo/hand.npz --preview demo/hand.png
	$(RELIGHT) fit-geometry --pose relaxed --two-hands -o demo/hands2.npz --preview demo/hands2.png
	# real hand motion (if ../shared/data is here): a Leap Motion pinch, every 10th frame fitted, the
	# frames between filled by slerp; rendered open (frame 0), closing (90) and pinched (180), palm side,
	# in one process (--frames A:B:S: the model, BVH and caches are built once)
	if [ -f $(SHARED)/hands/leap/pinch.json ]; then \
	  $(RELIGHT) fit-geometry --keypoints $(SHARED)/hands/leap/pinch.json --frames 0:300:10 \
	    --interpolate -o demo/leap_hand.npz --report demo/leap_fit.json && \
	  $(RELIGHT) camera --eye -0.2,0.0,-0.2 --target 0.03,0.16,0.03 --fov 35 --size 256x256 -o demo/leap_cam.json && \
	  $(RELIGHT) relight demo/leap_hand.npz builtin:studio --model physical --camera demo/leap_cam.json \
	    --frames 0:181:90 -o 'demo/leap_hand_{frame}.exr' --preview 'demo/leap_hand_{frame}.png'; \
	fi
	# texel-aligned, visibility-aware shading features under two environments (visibility traced once)
	$(RELIGHT) bake-features demo/hand.npz builtin:sky builtin:studio -o 'demo/feats_{env}.exr' \
		--per-vertex 'demo/feats_{env}.npz' --preview 'demo/feats_{env}.png' --specular both
	$(RELIGHT) bake-features builtin:two:fist builtin:sky -o demo/feats_two_fist.exr --preview demo/feats_two_fist.png
	# the physically based render of the default hand (the URHand physical baseline), with AOVs
	$(RELIGHT) relight demo/hand.npz builtin:studio --model physical -o demo/hand_physical.exr \
		--preview demo/hand_physical.png --aov normal,uv,depth
	# cameras: a ring of 8 around the hand, one of them picked to render the hand (the EXR header
	# records it: worldToCamera, worldToNDC), and that camera read back from the render
	$(RELIGHT) camera --orbit 8 --radius 0.4 --elevation 25 --target 0,0.03,0.02 --fov 30 --size 192x192 -o demo/hand_orbit.json
	$(RELIGHT) camera --from demo/hand_orbit.json --select cam001 -o demo/hand_cam001.json
	$(RELIGHT) relight demo/hand.npz builtin:studio --model physical --camera demo/hand_cam001.json \
		-o demo/hand_cam001.exr --preview demo/hand_cam001.png
	$(RELIGHT) camera --from demo/hand_cam001.exr -o demo/hand_cam001_from_exr.json
	# a small synthetic light-stage capture (fully lit + grouped-light frames, held-out env renders)
	$(RELIGHT) synth-capture -o demo/capture --cameras 6 --leds 32 --n-frames 6 --size 96 --eval-poses 1 --eval-cameras 2 \
		--preview demo/capture.png
	# RelightableHands' OLAT teacher learned from that capture (tiny preset, ~1 min), with its
	# validation scores; rendered under an env map (a sum over 16x32 directions) and one near point light
	$(RELIGHT) train-teacher demo/capture -o demo/teacher.pt --preset tiny --metrics-out demo/teacher_val.json
	printf '{"format": "relight/lights", "version": 1, "lights": [{"position": [0.3, 0.5, 0.6], "color": [1.0, 0.9, 0.8], "intensity": 0.6}]}\n' > demo/teacher_light.json
	$(RELIGHT) relight demo/capture/hand.npz builtin:studio --model teacher --checkpoint demo/teacher.pt \
		-o demo/hand_teacher_env.exr --preview demo/hand_teacher_env.png
	$(RELIGHT) relight demo/capture/hand.npz --lights demo/teacher_light.json --model teacher \
		--checkpoint demo/teacher.pt -o demo/hand_teacher_point.exr --preview demo/hand_teacher_point.png
	# URHand's linear lighting model with its physical branch, trained on the grouped frames only,
	# rendering an env map in one pass (no distillation)
	$(RELIGHT) train-teacher demo/capture --model linear -o demo/linear.pt --preset tiny --metrics-out demo/linear_val.json
	$(RELIGHT) relight demo/capture/hand.npz builtin:studio --model linear --checkpoint demo/linear.pt \
		-o demo/hand_linear_env.exr --preview demo/hand_linear_env.png
	# the same near point light through the linear model: its shading features carry the light's
	# direction and shadows, so even 150 iterations draw one light (the tiny teacher's is still flat)
	$(RELIGHT) relight demo/capture/hand.npz --lights demo/teacher_light.json --model linear \
		--checkpoint demo/linear.pt -o demo/hand_linear_point.exr --preview demo/hand_linear_point.png
	# URHand's quick personalisation (Sec. 5.4, supp. 9): a phone scan of a new subject (another skin)
	# under the sky, fitted and unwrapped into its mean texture, rendered by the linear model as it is
	$(RELIGHT) synth-capture builtin:right --skin-seed 9 --phone-scan builtin:sky --views 4 --size 128 \
		--tex-res 64 --aa 1 -o demo/scan
	$(RELIGHT) personalize demo/scan/view_*.exr --cameras demo/scan/cameras.json \
		--keypoints demo/scan/keypoints.json --env builtin:sky --checkpoint demo/linear.pt --iterations 60 \
		-o demo/me.npz --report demo/me_fit.json --preview demo/me_fit.png
	$(RELIGHT) relight demo/me.npz builtin:studio --model linear --checkpoint demo/linear.pt \
		-o demo/me_linear_env.exr --preview demo/me_linear_env.png
	# RelightableHands' student distilled from the teacher under env maps (one held out for
	# evaluation), rendered in one pass from bake-features' texel maps, on one hand and on two
	$(RELIGHT) distill demo/teacher.pt demo/capture --envs builtin:sky --envs builtin:studio \
		--envs builtin:uniform --envs builtin:point -o demo/student.pt --preset tiny --metrics-out demo/student_val.json
	$(RELIGHT) relight demo/capture/hand.npz builtin:studio --model student --checkpoint demo/student.pt \
		-o demo/hand_student_env.exr --preview demo/hand_student_env.png
	$(RELIGHT) relight builtin:two:fist builtin:sky --model student --checkpoint demo/student.pt \
		-o demo/hands2_student_env.exr --preview demo/hands2_student_env.png
	# the student with a head linear in its features (ours), in closed form: the per-texel
	# least-squares fit of the teacher's textures by the features, no training step (seconds)
	printf '{"head": "linear", "head_init": "lsq"}\n' > demo/student_lsq.json
	$(RELIGHT) distill demo/teacher.pt demo/capture --envs builtin:sky --envs builtin:studio \
		--envs builtin:uniform --envs builtin:point -o demo/student_lsq.pt --preset tiny \
		--config demo/student_lsq.json --iters 0 --metrics-out demo/student_lsq_val.json
	$(RELIGHT) relight demo/capture/hand.npz builtin:studio --model student --checkpoint demo/student_lsq.pt \
		-o demo/hand_lsq_student_env.exr --preview demo/hand_lsq_student_env.png
	# spherical-harmonic light probes
	$(RELIGHT) sh-probe builtin:studio --degree 2 -o demo/studio_probe.json --preview demo/studio_probe.png
	$(RELIGHT) sh-probe builtin:sky --degree auto --window hanning --max-degree 16 -o demo/sky_probe.json --preview demo/sky_probe.png
	# Gaussian avatar in a Gaussian room: a deep Gaussian shadow map, then relighting with shadows
	printf '{"format": "relight/lights", "version": 1, "lights": [{"position": [0.35, 1.3, 0.45], "color": [1.0, 0.95, 0.9], "intensity": 5.0}]}\n' > demo/lights.json
	$(RELIGHT) camera --eye 0.45,0.55,0.6 --target 0,0.15,0 --fov 45 --size 320x240 -o demo/room_cam.json
	$(RELIGHT) dgsm-build builtin:hand --translate 0,0.25,0 --receivers builtin:room --lights demo/lights.json \
		--size 512 -o demo/shadows.exr --occluders-out demo/hand_gaussians.ply --receivers-out demo/room.ply \
		--preview demo/shadows.png
	# the room's own light at the hand (paper Sec. 3.4: a probe fitted to the scene's cube faces there),
	# so the inserted hand (and the donut below) are lit as the room is; each before/after pair of previews
	# shares one exposure (--preview-exposure, the "before" picture's own auto scale) so the change shows.
	# The room's floor is lit by the lamp, which the probe (the room's surfaces seen from the hand) leaves
	# out: --direct-light adds it to the hand, or the hand is a dim brown with dark fingertips (they face
	# the room's open top); "before" is the same light with the floor's shadow off (--shadow-strength 0)
	$(RELIGHT) sh-probe demo/room.ply --at 0,0.3,0.02 --degree auto -o demo/room_probe.json --preview demo/room_probe.png
	$(RELIGHT) relight demo/hand_gaussians.ply --probe demo/room_probe.json --dgsm demo/shadows.exr --direct-light \
		--shadow-strength 0 --receivers demo/room.ply --camera demo/room_cam.json -o demo/room_before.exr \
		--preview demo/room_before.png --preview-exposure 0.43
	$(RELIGHT) relight demo/hand_gaussians.ply --probe demo/room_probe.json --dgsm demo/shadows.exr --direct-light \
		--receivers demo/room.ply --camera demo/room_cam.json -o demo/room_after.exr --preview demo/room_after.png --preview-exposure 0.43
	# the real donut (if ../shared/data is here) inserted beside the hand: fitted to 15 cm, laid flat
	# on the floor; one deep Gaussian shadow map per object, relit by the room's probe without/with shadows,
	# then with the lamp lighting the objects too (--direct-light; the shadows take the lamp's share, auto)
	if [ -f $(SHARED)/gaussians/donut-fused.ply ]; then \
	  printf '{"format": "relight/lights", "version": 1, "lights": [{"position": [-0.45, 1.2, -0.25], "color": [1.0, 0.95, 0.9], "intensity": 5.0}]}\n' > demo/scene_lights.json && \
	  $(RELIGHT) camera --eye 0.6,0.5,0.65 --target 0.08,0.15,0.05 --fov 50 --size 400x300 -o demo/scene_cam.json && \
	  $(RELIGHT) dgsm-build 'builtin:hand:translate=0,0.25,0' '$(DONUT)' \
	    --receivers builtin:room --lights demo/scene_lights.json --size 512 -o demo/scene_shadows.exr \
	    --preview demo/scene_shadows.png --preview-camera demo/scene_cam.json && \
	  $(RELIGHT) relight 'builtin:hand:translate=0,0.25,0' --object '$(DONUT)' --probe demo/room_probe.json \
	    --receivers demo/room.ply --camera demo/scene_cam.json -o demo/scene_before.exr --preview demo/scene_before.png --preview-exposure 0.43 && \
	  $(RELIGHT) relight 'builtin:hand:translate=0,0.25,0' --object '$(DONUT)' --probe demo/room_probe.json \
	    --dgsm demo/scene_shadows.exr --receivers demo/room.ply --camera demo/scene_cam.json \
	    -o demo/scene_after.exr --preview demo/scene_after.png --preview-exposure 0.43 && \
	  $(RELIGHT) relight 'builtin:hand:translate=0,0.25,0' --object '$(DONUT)' --probe demo/room_probe.json \
	    --dgsm demo/scene_shadows.exr --receivers demo/room.ply --camera demo/scene_cam.json \
	    --direct-light -o demo/scene_lamp.exr --preview demo/scene_lamp.png --preview-exposure 0.43; \
	fi
	# the real robot (if ../shared/data is here) beside the hand in the room, with a lamp added (a
	# compact bright cluster of Gaussians): the light estimated from the scene (auto:1, paper
	# Sec. 3.1), one DGSM for hand + robot, the probe fitted from the scene at the robot (Sec. 3.4),
	# before/after renders on one exposure (the "before" picture's own auto scale, 0.408) and the
	# lighting metrics (Sec. 4.1); "before" is the robot relit by a uniform probe of radiance 1, i.e. its
	# captured colours; "after" adds the estimated lamp's direct light (--direct-light: the probe holds
	# only the room's surfaces, and without the lamp the hand is a dim brown)
	if [ -f $(SHARED)/gaussians/playbot-lod3.ply ]; then \
	  $(RELIGHT) camera --eye 0.45,0.45,0.7 --target -0.1,0.13,0.05 --fov 50 --size 400x300 -o demo/robot_cam.json && \
	  $(PY) -c "import numpy as np; from relight_cli.gaussians.from_mesh import load_gaussians; from relight_cli.formats.gaussians_ply import Gaussians, concatenate, rgb_to_sh_dc, write_gaussians; n = 40; lamp = Gaussians(np.array([0.35, 1.3, 0.45]) + np.random.default_rng(0).normal(0, 0.015, (n, 3)), np.full((n, 3), 0.01), np.tile([1.0, 0, 0, 0], (n, 1)), np.full(n, 0.95), rgb_to_sh_dc(np.tile([6.0, 5.6, 5.0], (n, 1)))[:, None, :], 0); write_gaussians('demo/room_lamp.ply', concatenate([load_gaussians('builtin:room'), lamp]))" && \
	  $(RELIGHT) dgsm-build 'builtin:hand:translate=0,0.25,0' '$(ROBOT)' --receivers demo/room_lamp.ply \
	    --lights auto:1 --lights-out demo/robot_lights.json --size 256 -o demo/robot_shadows.exr \
	    --preview demo/robot_shadows.png && \
	  $(RELIGHT) sh-probe demo/room_lamp.ply --at -0.25,0.12,0.1 --degree 2 -o demo/robot_probe.json \
	    --preview demo/robot_probe.png && \
	  $(RELIGHT) sh-probe builtin:uniform --degree 0 -o demo/uniform_probe.json && \
	  $(RELIGHT) relight '$(ROBOT)' --probe demo/uniform_probe.json -o demo/robot_before.ply && \
	  $(RELIGHT) relight '$(ROBOT)' --probe demo/robot_probe.json -o demo/robot_relit.ply && \
	  $(RELIGHT) relight 'builtin:hand:translate=0,0.25,0' --object '$(ROBOT)' --probe demo/uniform_probe.json \
	    --receivers demo/room_lamp.ply --camera demo/robot_cam.json -o demo/robot_before.exr --preview demo/robot_before.png \
	    --preview-exposure 0.408 && \
	  $(RELIGHT) relight 'builtin:hand:translate=0,0.25,0' --object '$(ROBOT)' --probe demo/robot_probe.json \
	    --dgsm demo/robot_shadows.exr --direct-light --receivers demo/room_lamp.ply --camera demo/robot_cam.json \
	    -o demo/robot_after.exr --preview demo/robot_after.png --preview-exposure 0.408 && \
	  $(RELIGHT) metrics lighting --scene demo/room_lamp.ply --avatar demo/robot_before.ply \
	    --relit demo/robot_relit.ply --radius 1.5 -o demo/robot_lighting.json; \
	fi
	# animated avatars (the DGSM paper's setting), one process per clip: the Leap pinch as Gaussians
	# moving over the room; per frame the shadow map rebuilt from the moved hand (--lights) and its
	# probe refitted at the hand from the room (--probe scene, Sec. 3.4); per-frame EXRs and previews,
	# and the clip as an animated WebP with one exposure; then PlayCanvas' flipbook monkey (a per-frame
	# PLY pattern written by another tool: it turns, grows and changes colour) on the floor
	if [ -f demo/leap_hand.npz ]; then \
	  mkdir -p demo/clip && \
	  $(RELIGHT) relight 'demo/leap_hand.npz:translate=0,0.05,0' --frames 0:291:24 --receivers builtin:room \
	    --lights demo/lights.json --probe scene --direct-light --camera demo/room_cam.json \
	    -o 'demo/clip/hand_{frame:03d}.exr' --preview 'demo/clip/hand_{frame:03d}.png' --video demo/clip_hand.webp; \
	fi
	if [ -d $(SHARED)/gaussians/sequences/flipbook-monkey ]; then \
	  mkdir -p demo/clip && \
	  $(RELIGHT) relight '$(SHARED)/gaussians/sequences/flipbook-monkey/frame_{frame:04d}.ply:fit=0.3;on-floor' \
	    --frames all --receivers builtin:room --lights demo/lights.json --probe scene --direct-light \
	    --camera demo/room_cam.json -o 'demo/clip/monkey_{frame}.exr' --video demo/clip_monkey.png; \
	fi
	# quality metrics of a cube round trip against direct resampling, and the regression gate
	$(RELIGHT) envmap builtin:sky --to cube --size 32 -o demo/sky_cube.exr
	$(RELIGHT) envmap demo/sky_cube.exr --to latlong --size 128x64 -o demo/sky_back.exr
	$(RELIGHT) envmap builtin:sky --to latlong --size 128x64 -o demo/sky_direct.exr
	$(RELIGHT) metrics image demo/sky_back.exr demo/sky_direct.exr --space srgb -o demo/metrics_envmap.json \
		--preview demo/metrics_envmap.png
	# the real donut (if ../shared/data is here) relit by two probes, both previews on one exposure
	# (--preview-exposure: the "before" picture's own auto scale, 0.7) so the brighter studio light shows
	if [ -f $(SHARED)/gaussians/donut-fused.ply ]; then \
	  $(RELIGHT) camera --eye 0,0.25,0.3 --target 0,0,0.03 --fov 45 --size 256x192 -o demo/donut_cam.json && \
	  $(RELIGHT) sh-probe builtin:uniform --degree 0 -o demo/uniform_probe.json && \
	  $(RELIGHT) relight $(SHARED)/gaussians/donut-fused.ply --probe demo/uniform_probe.json --camera demo/donut_cam.json -o demo/donut_before.exr --preview demo/donut_before.png --preview-exposure 0.7 && \
	  $(RELIGHT) relight $(SHARED)/gaussians/donut-fused.ply --probe demo/studio_probe.json --intensity 2 --camera demo/donut_cam.json -o demo/donut_after.exr --preview demo/donut_after.png --preview-exposure 0.7; \
	fi
	@echo "demo outputs are in demo/"

# The README's example pipeline, exactly as written there (tools/readme_example.py extracts
# it); outputs in example/.  Needs ../shared/data (a Poly Haven HDRI and the 3DGS donut).
# Its `metrics compare` of the student against its teacher may print "N regressed" and exit
# 3 (the tiny student scores below its teacher): expected, and the pipeline says so.
example: install
	$(PY) tools/readme_example.py
	@echo "example outputs are in example/"

# One pytest-xdist worker per core, each test file kept on one worker (its module and
# session fixtures are built once), the slowest files handed out first (tests/conftest.py,
# which also gives each worker one thread).
TEST_WORKERS ?= 2
test: install
	$(PY) -m pytest -n $(TEST_WORKERS) --dist loadfile --no-loadscope-reorder

man: install
	$(PY) -m relight_cli.cli.manpage man
	mkdir -p $(VENV)/share/man/man1 && cp man/*.1 $(VENV)/share/man/man1/

# Every benchmark writes its table, data and plot under $(BENCH_OUT); QUICK=1 runs the
# smoke versions (a few minutes in all, see benchmarks/README.md).  matplotlib comes
# with the optional extra [bench].
BENCH_OUT ?= benchmarks/out
BENCH_STAMP := $(VENV)/.bench-stamp
$(BENCH_STAMP): $(STAMP)
	$(PY) -m pip install -q -e '.[bench]'
	touch $(BENCH_STAMP)

benchmarks: $(BENCH_STAMP)
	@for b in benchmarks/bench_*.py; do echo "== $$b"; \
	  $(PY) $$b --out $(BENCH_OUT) $(if $(QUICK),--quick) || exit 1; done

# The papers' comparison tables (benchmarks/README.md): SCALE=tiny|medium (paper: a GPU job),
# one process per paper; the tables go to benchmarks/results.
SCALE ?= medium
study: $(BENCH_STAMP)
	nice -n 5 $(PY) benchmarks/study_hands.py --scale $(SCALE) --seeds 3 --out benchmarks/out/study_$(SCALE) \
		--results benchmarks/results --tables rh_t13,rh_t2 & first=$$!; \
	nice -n 5 $(PY) benchmarks/study_hands.py --scale $(SCALE) --seeds 3 --out benchmarks/out/study_$(SCALE) \
		--results benchmarks/results --tables ur_t2,ur_t3 && wait $$first

clean:
	rm -rf demo example build *.egg-info .pytest_cache
