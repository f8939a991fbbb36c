"""Library scene builders (validation cases with analytic references, peer throughput scenes)."""
