"""Library behind the command-line tools that are not the pipeline itself: batch evaluation and its executors,
the benchmark, dataset conversion, a bag's topics, the generated config reference."""
