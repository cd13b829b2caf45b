"""core package.

Large CPU tensors get transparent huge pages (PyTorch's THP_MEM_ALLOC_ENABLE, read once, at torch's first
allocation, so it is set here, before any core module imports torch): each big temporary of a render or a training
step is a fresh mapping that the kernel faults in page by page, and in 2 MB pages that costs a 512th of the faults.
A fox field forward on 212k points (worker thread, 2 threads) took 126 ms in 4 KB pages and 84 ms in 2 MB ones.
Set it to 0 to opt out; where the kernel's THP mode is 'never' it changes nothing.
"""
import os as _os

THP_ENV = "THP_MEM_ALLOC_ENABLE"
THP_FROM_USER = THP_ENV in _os.environ  # else ours: a checkout benchmarked beside this one must not inherit it
_os.environ.setdefault(THP_ENV, "1")
