"""Testing: the test protocol, rollouts, records, metrics, which AC is tested, replays, sweeps."""
