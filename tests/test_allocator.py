import platform

from dswm.pipeline.allocator import keep_freed_memory


def test_the_allocator_keeps_freed_memory_on_glibc_and_is_left_alone_elsewhere():
    assert keep_freed_memory() is (platform.libc_ver()[0] == "glibc")
