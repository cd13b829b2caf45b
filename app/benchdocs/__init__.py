"""The README's figure table and docs/BENCHMARKS.md, generated from the benches' JSON (`repaint-nerf docs`)."""
