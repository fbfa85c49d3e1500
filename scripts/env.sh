# Sourced by the scripts: one build folder outside the clone, shared by CI, tests,
# benchmarks and the quick start, so faer is compiled once per machine.
export CARGO_TARGET_DIR="${CARGO_TARGET_DIR:-/var/tmp/crispen-target}"
export CARGO_TERM_COLOR="${CARGO_TERM_COLOR:-never}"
