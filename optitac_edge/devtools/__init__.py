"""Developer tools: the benchmark, the soak run and the paper's method done literally (the oracle).

Never imported by the runtime.
"""
