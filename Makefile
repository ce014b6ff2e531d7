# artrack — the two commands the README opens with: `make demo` and `make test`.
# Each sets up what is missing first (idempotent): .venv, wheel fix, colcon build.
SHELL := /bin/bash
ENV := . scripts/env.sh &&
DEMO_BAG := bags/demo.mcap
DEMO_OUT := out/demo-synth
# The real recording (Pose2Sim Demo_SinglePerson, fetched by `make data`), at quarter size.
REAL_DEMO := .cache/pose2sim/Pose2Sim/Demo_SinglePerson
REAL_BAG := bags/pose2sim_single.mcap
REAL_OUT := out/demo
REAL_SCALE := 0.25

.PHONY: setup data test demo demo-synth lint bench clean

setup:
	@bash scripts/setup.sh

# Real 4-camera recordings with calibration (pose2sim wheel, data only; cached in .cache/).
data: setup
	@bash scripts/fetch_pose2sim.sh >/dev/null

lint: setup
	@$(ENV) ruff check src tests bench

test: setup data
	@$(ENV) ruff check src tests bench
	@$(ENV) python -m pytest tests -q -p no:cacheprovider -n 2 --dist loadfile

# The main job, on a real recording: convert the four Qualisys videos + calibration into
# a bag once (quarter size, CompressedImage + CameraInfo), replay it through the node
# graph (blob features per camera, skeleton, feedback projection) as separate processes
# over DDS in lockstep, record the output bag, then print frames per second and the
# checks without ground truth (bench/real_video.py: IoU with an independent foreground,
# joints inside it, leave-one-camera-out, joint speeds) and write the overlay montage and
# video to out/demo/. Tunables for this recording: config/pose2sim_demo.yaml (blob tracker),
# config/pose2sim_skeleton.yaml (estimator) and config/pose2sim_body_model.yaml (body model).
demo: setup data
	@mkdir -p $(REAL_OUT) bags
	@$(ENV) [ -e $(REAL_BAG) ] || artrack bag-from-videos --videos $(REAL_DEMO)/videos/cam0{1,2,3,4}.mp4 \
		--calib $(REAL_DEMO)/calibration/Calib.qca.txt --scale $(REAL_SCALE) --out $(REAL_BAG) --quiet
	@rm -rf $(REAL_OUT)/graph $(REAL_OUT)/logs
	@$(ENV) artrack launch config/graph.yaml --set bag=$(REAL_BAG) --set out=$(REAL_OUT)/graph --set fps=60.0 \
		--set blob_config=$(CURDIR)/config/pose2sim_demo.yaml \
		--set skeleton_config=$(CURDIR)/config/pose2sim_skeleton.yaml \
		--set body_model=$(CURDIR)/config/pose2sim_body_model.yaml --log-dir $(REAL_OUT)/logs
	@grep -ho "done: .*frames per second.*" $(REAL_OUT)/logs/bag_player.log | sed 's/^done: /graph: /'
	@$(ENV) python bench/real_video.py --bag $(REAL_BAG) --pred $(REAL_OUT)/graph --quiet \
		--overlay-png $(REAL_OUT)/overlay.png --overlay-mp4 $(REAL_OUT)/overlay.mp4
	@echo "demo outputs in $(REAL_OUT)/"

# The synthetic demo (ground truth, MPJPE): synthesise a 4-camera scene, run the same
# graph on it, print fps and MPJPE, write the overlay montage and the error-over-time plot
# to out/demo-synth/. With the edge features (`edges=true`, ALGORITHMS.md §2 "Fusion"): on
# this bag offline 67.1 mm with blobs alone, 42.4 mm with edges (`artrack track [--edges]`).
demo-synth: setup
	@mkdir -p $(DEMO_OUT) bags
	@$(ENV) [ -e $(DEMO_BAG) ] || artrack synth --seed 0 --image-format jpeg --out $(DEMO_BAG)
	@rm -rf $(DEMO_OUT)/graph $(DEMO_OUT)/logs
	@$(ENV) artrack launch config/graph.yaml --set bag=$(DEMO_BAG) --set out=$(DEMO_OUT)/graph --set edges=true \
		--log-dir $(DEMO_OUT)/logs
	@grep -ho "done: .*frames per second.*" $(DEMO_OUT)/logs/bag_player.log | sed 's/^done: /graph: /'
	@$(ENV) artrack eval --truth $(DEMO_BAG) --pred $(DEMO_OUT)/graph --plot $(DEMO_OUT)/error_over_time.png
	@$(ENV) artrack overlay $(DEMO_BAG) --pred $(DEMO_OUT)/graph --out $(DEMO_OUT)/overlay.png
	@echo "demo outputs in $(DEMO_OUT)/"

# Numbers behind the issue notes (each script prints a table and one JSON line; ~45 min in all).
bench: setup
	@$(ENV) python bench/edge_scaling.py
	@$(ENV) python bench/edge_tracking.py --duration 10 --sizes 320x240
	@$(ENV) python bench/closed_loop.py
	@$(ENV) python bench/blob_tracker.py
	@$(ENV) python bench/real_video.py

clean:
	rm -rf ros2_ws/build ros2_ws/install ros2_ws/log out
