"""The process and the machine, not the method: the allocator setting and bfloat16 support (:mod:`.perf`), what a
figure ran on (:mod:`.machine`), what Lightning prints that is left out of the console (:mod:`.console`)."""
