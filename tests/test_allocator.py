"""The live loop's allocator setting."""

import platform

from core.allocator import keep_freed_memory


def test_freed_memory_is_kept_where_the_c_library_is_glibc():
    assert keep_freed_memory() is (platform.libc_ver()[0] == "glibc")
