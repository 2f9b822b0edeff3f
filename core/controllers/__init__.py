"""Visual servo controllers: classic IBVS, PBVS, 2.5D and the switching IBVS with laser."""
