"""``fitme bench``: what accuracy costs in time (synthetic ground truth and real photos), the whole-fit
stability suite and the CI regression run (docs/benchmarks.md)."""
