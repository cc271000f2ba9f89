"""Games and data: example game files, scenario generators, dataset files, CLI. No torch."""
