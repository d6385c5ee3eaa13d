"""The joint variational solver (paper sections 3-4; README "How it works")."""
