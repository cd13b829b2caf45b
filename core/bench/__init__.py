"""Benchmark measurements: functions that run a measurement and return its figures as dicts (no argparse,
printing or plots); their drivers live in app/bench/ (see app/commands/bench.py)."""
