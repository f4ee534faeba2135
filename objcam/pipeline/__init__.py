"""The stage engine: a graph of stages, each a plain function; the engine owns paths, caching and locks."""
