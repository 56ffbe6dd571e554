// Under AddressSanitizer: let lcmx install its SIGBUS guard (ASan otherwise ignores a
// program's sigaction for the signals it handles; shm_core_test.cpp truncates a segment under
// a reader). Unused in other builds.
extern "C" const char* __asan_default_options() { return "allow_user_segv_handler=1"; }
