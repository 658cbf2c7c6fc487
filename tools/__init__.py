"""Roadwatch tools: the command line, the field config tool and the lab tools (simulator, replay, evaluation, benchmarks)."""
