# Included by the subset packages of ROS distribution packages (control_msgs, tf2_msgs) before anything is
# generated. Why: in a workspace on top of a ROS installation that already has the full package, installing our
# subset over it would hide every type the subset does not define. A prefix on AMENT_PREFIX_PATH other than this
# build's own install that registers the package (ament index) means "the environment has it": nothing is built
# or installed, and that prefix's package stays the one found. tools/build-interfaces installs into the venv, the
# only prefix on its AMENT_PREFIX_PATH, so there the subset is always built.
macro(mds_skip_if_installed_elsewhere)
  get_filename_component(_mds_own_prefix "${CMAKE_INSTALL_PREFIX}" REALPATH)
  string(REPLACE ":" ";" _mds_prefixes "$ENV{AMENT_PREFIX_PATH}")
  foreach(_mds_prefix IN LISTS _mds_prefixes)
    if(_mds_prefix)
      get_filename_component(_mds_real "${_mds_prefix}" REALPATH)
      if(NOT _mds_real STREQUAL _mds_own_prefix
         AND EXISTS "${_mds_real}/share/ament_index/resource_index/packages/${PROJECT_NAME}")
        message(STATUS "${PROJECT_NAME} is already installed in ${_mds_prefix}: this subset is not built")
        return()
      endif()
    endif()
  endforeach()
endmacro()
