// Input errors raised by the C++ core (bound to Python ValueError).
#pragma once

#include <stdexcept>
#include <string>

namespace bubble {

// Thrown for malformed input; bound to Python's ValueError.
struct InputError : std::invalid_argument {
  using std::invalid_argument::invalid_argument;
};

inline void require(bool ok, const std::string& what) {
  if (!ok) throw InputError(what);
}

}  // namespace bubble
