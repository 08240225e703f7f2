"""The process and the machine, not the method: the allocator setting and bfloat16 support (:mod:`.perf`), what a
figure ran on (:mod:`.machine`)."""
