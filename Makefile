# The two commands of the README's quick start. Both set up .venv first (idempotent).
.PHONY: setup demo test lint test-gamma

setup:
	@bash deploy/setup.sh

demo: setup
	.venv/bin/splittag demo

lint: setup
	.venv/bin/ruff check .
	.venv/bin/ruff format --check .
	.venv/bin/mypy

test: lint
	.venv/bin/pytest

# The suite again with the robot's compute at 2x and 0.5x (see deploy/test-gamma.sh).
test-gamma: setup
	bash deploy/test-gamma.sh
