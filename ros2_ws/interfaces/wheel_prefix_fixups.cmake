# Injected by scripts/build_interfaces.sh with -DCMAKE_PROJECT_INCLUDE=<this file>; not part of the packages.
#
# The ros-jazzy-* wheels on PyPI were built in a manylinux container, and the CMake targets they export for their
# Python bindings (<pkg>::<pkg>__rosidl_generator_py) still name that container's include folders
# (/opt/python/cp311-cp311/include/python3.11 and its numpy include folder). CMake refuses to generate when an
# imported target names a folder that does not exist. The generated bindings take the Python and numpy include
# folders of the interpreter they are built for from their own target, so those stale entries are dropped here,
# once every find_package() of the project has run (a deferred call at the end of the top-level CMakeLists.txt).

function(_wheel_prefix_drop_missing_include_dirs)
  get_directory_property(_targets DIRECTORY "${CMAKE_SOURCE_DIR}" IMPORTED_TARGETS)
  foreach(_target IN LISTS _targets)
    get_target_property(_dirs ${_target} INTERFACE_INCLUDE_DIRECTORIES)
    if(NOT _dirs)
      continue()
    endif()
    set(_kept "")
    set(_dropped "")
    foreach(_dir IN LISTS _dirs)
      # generator expressions and folders that exist are kept as they are
      if(_dir MATCHES "^\\$<" OR EXISTS "${_dir}")
        list(APPEND _kept "${_dir}")
      else()
        list(APPEND _dropped "${_dir}")
      endif()
    endforeach()
    if(_dropped)
      set_target_properties(${_target} PROPERTIES INTERFACE_INCLUDE_DIRECTORIES "${_kept}")
      message(VERBOSE "${_target}: dropped missing include folders ${_dropped}")
    endif()
  endforeach()
endfunction()

cmake_language(DEFER DIRECTORY "${CMAKE_SOURCE_DIR}" CALL _wheel_prefix_drop_missing_include_dirs)
