"""Benchmarks of the jaxfusion engine: `python -m bench [--quick]`. See bench/RESULTS.md."""
