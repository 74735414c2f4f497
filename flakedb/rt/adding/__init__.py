"""Adding-doubling: layers, the stack's parts and channels, order-by-order and blocked solves, the whole stack
and its solved BSDF, the inputs' checks, and what a series of solves shares (paper eq. 3-4, docs/model.md §1, §4)."""
