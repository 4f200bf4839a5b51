# Loaded before each interface package's project() (CMAKE_PROJECT_INCLUDE, tools/build-interfaces).
#
# Why: the ROS wheels' exported CMake targets name the include directories of the machine they were built on
# (/opt/python/cp311-cp311/include/python3.11, .../site-packages/numpy/_core/include), and CMake refuses a
# target that names a directory that does not exist. At the end of the package's CMakeLists (deferred call),
# every imported target's missing Python / numpy include directory is replaced by this venv's
# (MDS_PYTHON_INCLUDE, MDS_NUMPY_INCLUDE). Nothing in the prefix is modified.

function(mds_fix_wheel_include_dirs)
  get_directory_property(targets DIRECTORY "${CMAKE_SOURCE_DIR}" IMPORTED_TARGETS)
  foreach(target IN LISTS targets)
    get_target_property(dirs ${target} INTERFACE_INCLUDE_DIRECTORIES)
    if(NOT dirs)
      continue()
    endif()
    set(fixed "")
    set(changed FALSE)
    foreach(dir IN LISTS dirs)
      if(NOT dir MATCHES "^\\$<" AND NOT EXISTS "${dir}")
        if(dir MATCHES "/numpy/_core/include$" OR dir MATCHES "/numpy/core/include$")
          set(dir "${MDS_NUMPY_INCLUDE}")
          set(changed TRUE)
        elseif(dir MATCHES "/include/python3\\.[0-9]+$")
          set(dir "${MDS_PYTHON_INCLUDE}")
          set(changed TRUE)
        endif()
      endif()
      list(APPEND fixed "${dir}")
    endforeach()
    if(changed)
      set_target_properties(${target} PROPERTIES INTERFACE_INCLUDE_DIRECTORIES "${fixed}")
    endif()
  endforeach()
endfunction()

if(NOT MDS_PYTHON_INCLUDE OR NOT MDS_NUMPY_INCLUDE)
  message(FATAL_ERROR "wheel_paths.cmake needs -DMDS_PYTHON_INCLUDE=... and -DMDS_NUMPY_INCLUDE=...")
endif()
cmake_language(DEFER DIRECTORY "${CMAKE_SOURCE_DIR}" CALL mds_fix_wheel_include_dirs)
