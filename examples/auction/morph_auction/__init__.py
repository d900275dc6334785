"""morph-auction: a single-item auction allocator for morph-sim, written against its public policy interface only."""
