// Stubs for sick_scan_xd's logging/diagnostic hooks, which live in the driver's API and launcher
// files (api_impl.cpp, sick_generic_laser.cpp) that this harness does not build. They only route
// log text; none of them touches scan data.
#include <cstdarg>
#include <cstdio>
#include <iostream>
#include <string>
#include <sick_scan/sick_ros_wrapper.h>

std::string vargs_to_string(const char* const format, ...)
{
  char buf[4096];
  va_list args;
  va_start(args, format);
  std::vsnprintf(buf, sizeof(buf), format, args);
  va_end(args);
  return std::string(buf);
}
void setDiagnosticStatus(SICK_DIAGNOSTIC_STATUS, const std::string& message) { std::cerr << "diagnostic: " << message << "\n"; }
void notifyLogMessageListener(int level, const std::string& message) { if (level >= 2) std::cerr << "log(" << level << "): " << message << "\n"; }
int32_t getVerboseLevel() { return 9; } // above every level: the driver's own console printing stays quiet
