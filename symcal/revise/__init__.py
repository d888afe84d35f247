"""Model revision: diagnose a result, candidate effects and variants, the improve loop,
the ladder."""
