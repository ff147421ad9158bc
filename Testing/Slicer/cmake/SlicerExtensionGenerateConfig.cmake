# Stand-in for Slicer's extension description generation: the metadata must be there.
foreach(variable EXTENSION_CATEGORY EXTENSION_DESCRIPTION EXTENSION_CONTRIBUTORS EXTENSION_DEPENDS)
  if("${${variable}}" STREQUAL "")
    message(FATAL_ERROR "${variable} is not set")
  endif()
endforeach()
file(WRITE "${CMAKE_BINARY_DIR}/standin-extension.txt"
  "category=${EXTENSION_CATEGORY}\ndescription=${EXTENSION_DESCRIPTION}\n"
  "contributors=${EXTENSION_CONTRIBUTORS}\ndepends=${EXTENSION_DEPENDS}\n"
  "icon=${EXTENSION_ICONURL}\nscreenshots=${EXTENSION_SCREENSHOTURLS}\n")
