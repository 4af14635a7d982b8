"""volshade benchmarks: `python -m benchmarks.run NAME [--quick] [--json OUT]`."""
