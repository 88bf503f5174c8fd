# Writes OUT, a header defining DOJO_GIT_COMMIT: the checkout's commit, with "-dirty" when tracked
# files differ from it. Run at every build (not at configure time) so that `dojo version` and the
# benchmark records name the code that was built; the header is rewritten only when the commit
# changes, so an unchanged checkout recompiles nothing.
# Only the project's own repository counts: a tree exported into another git checkout (a vendored
# copy, a monorepo) would otherwise report that repository's commit as ours.
execute_process(
  COMMAND git rev-parse --show-toplevel
  WORKING_DIRECTORY ${SOURCE_DIR}
  OUTPUT_VARIABLE toplevel OUTPUT_STRIP_TRAILING_WHITESPACE ERROR_QUIET)
if(toplevel)
  file(REAL_PATH "${toplevel}" toplevel)
endif()
file(REAL_PATH "${SOURCE_DIR}" source)
set(commit "")
if(toplevel STREQUAL source)
  execute_process(
    COMMAND git rev-parse --short=12 HEAD
    WORKING_DIRECTORY ${SOURCE_DIR}
    OUTPUT_VARIABLE commit OUTPUT_STRIP_TRAILING_WHITESPACE ERROR_QUIET
    RESULT_VARIABLE failed)
endif()
if(failed OR NOT commit)
  set(commit "unknown")  # a source tree without a repository of its own (an archive, an exported copy)
else()
  execute_process(COMMAND git diff --quiet HEAD -- WORKING_DIRECTORY ${SOURCE_DIR} RESULT_VARIABLE dirty)
  if(dirty)
    set(commit "${commit}-dirty")
  endif()
endif()
set(text "#pragma once\n#define DOJO_GIT_COMMIT \"${commit}\"\n")
if(EXISTS ${OUT})
  file(READ ${OUT} old)
endif()
if(NOT old STREQUAL text)
  file(WRITE ${OUT} "${text}")
endif()
