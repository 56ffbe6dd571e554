# libsodium (Debian: libsodium-dev), the group keys' cryptography (lcmx::udpm, docs/keyed-groups.md).
# Debian ships no CMake package for it: found with pkg-config as the imported target
# PkgConfig::lcmx_sodium. Included by lcmx's own build and by the installed lcmxConfig.cmake
# (a static lcmx::udpm links it).
if(NOT TARGET PkgConfig::lcmx_sodium)
  find_package(PkgConfig REQUIRED)
  pkg_check_modules(lcmx_sodium REQUIRED IMPORTED_TARGET GLOBAL libsodium>=1.0.18)
endif()
