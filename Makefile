# The two commands of the README's quick start. Both set up .venv first (idempotent).
.PHONY: setup demo test lint

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
