# The two set-up commands of the README:
#   make demo   installs everything, then replays the bundled bag through the live nodes and queries it
#   make test   installs everything, then runs lint and the whole test suite
.PHONY: install demo test lint bench
install:
	bash scripts/install.sh
demo: install
	bash scripts/with_env.sh monovoc demo
test: install
	bash scripts/with_env.sh bash scripts/run_tests.sh
lint: install
	.venv/bin/ruff check .
bench: install
	bash scripts/with_env.sh python benchmarks/bench_scd.py
