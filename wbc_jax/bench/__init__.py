"""Developer tooling: throughput and latency benchmarks, kernel traces, the QP audit against OSQP, test QPs."""
