# Stand-in for Slicer's extension packaging: nothing to package here.
file(APPEND "${CMAKE_BINARY_DIR}/standin-extension.txt" "cpack=included\n")
