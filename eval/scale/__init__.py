"""Scale: the Ray session, the benchmark grid on Ray Tune and Population Based Training."""
