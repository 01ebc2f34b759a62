"""Tests of the benchmarks (bench/): each one's arithmetic on made-up results, its harness on
a tiny scene, and that every benchmark is a module with run(), main() and --json."""
