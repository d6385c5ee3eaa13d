"""The joint variational solver (DESIGN section 2, paper sections 3-4)."""
