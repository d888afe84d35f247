"""The problem compiler: a problem spec into a symbolic Problem (CasADi SX) and its views."""
