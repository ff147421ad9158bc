# Stands in for the SlicerConfig.cmake of a Slicer build tree, to configure the extension's CMake
# files where no Slicer is built (Testing/Slicer/test_extension.py). It provides what the
# extension uses, with the real macros' checks (every listed file exists) and their copies (scripts
# and resources into the scripted-modules folder of the build tree), done at configure time.
set(Slicer_FOUND TRUE)
set(Slicer_VERSION "5.10.0")
set(Slicer_USE_PYTHONQT TRUE)
set(Slicer_QTSCRIPTEDMODULES_LIB_DIR "lib/Slicer-5.10/qt-scripted-modules")
set(Slicer_USE_FILE "${CMAKE_CURRENT_LIST_DIR}/UseSlicer.cmake")
set(Slicer_EXTENSION_GENERATE_CONFIG "${CMAKE_CURRENT_LIST_DIR}/SlicerExtensionGenerateConfig.cmake")
set(Slicer_EXTENSION_CPACK "${CMAKE_CURRENT_LIST_DIR}/SlicerExtensionCPack.cmake")
