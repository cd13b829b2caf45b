"""Benchmark drivers (`repaint-nerf bench NAME`): HELP, add_arguments and run for each benchmark, calling the
measurement in core/bench/ (or driving the editor and its worker directly: viewport, soak)."""
