// Feeds whole CoLa-B telegrams (one hex string per line on stdin, 02 02 02 02 + length + payload
// + XOR) to sick_scan_xd's own LMDscandata parser (parseCommonBinaryResultTelegram) configured
// as an LMS1xx, and prints the LaserScan it fills: one JSON object per telegram.
#include <cstdio>
#include <iostream>
#include <string>
#include <vector>
#include <sick_scan/sick_ros_wrapper.h>
#include <sick_scan/sick_scan_common.h>
#include <sick_scan/sick_lmd_scandata_parser.h>

int main(int argc, char** argv)
{
  std::string scanner = argc > 1 ? argv[1] : SICK_SCANNER_LMS_1XX_NAME;
  sick_scan_xd::SickGenericParser parser(scanner);
  std::string line;
  while (std::getline(std::cin, line))
  {
    if (line.empty())
      continue;
    std::vector<uint8_t> buf;
    for (size_t i = 0; i + 1 < line.size(); i += 2)
      buf.push_back((uint8_t)std::stoul(line.substr(i, 2), nullptr, 16));
    short elevAngleX200 = 0;
    double elevationAngleInRad = 0;
    rosTime recvTimeStamp(0, 0);
    bool fireEncoder = false;
    sick_scan_msg::Encoder encoderMsg;
    int numEchos = 0;
    std::vector<float> vang_vec, azimuth_vec;
    ros_sensor_msgs::LaserScan msg;
    // config_sw_pll_only_publish=true and use_generation_timestamp=true are the driver's defaults.
    bool ok = sick_scan_xd::parseCommonBinaryResultTelegram(buf.data(), (int)buf.size(), elevAngleX200, 1.0 / 200,
      elevationAngleInRad, recvTimeStamp, true, true, &parser, fireEncoder, encoderMsg, numEchos, vang_vec, azimuth_vec, msg);
    std::printf("{\"ok\": %s, \"num_echos\": %d, \"angle_min\": %.9g, \"angle_increment\": %.9g, \"angle_max\": %.9g, "
                "\"scan_time\": %.9g, \"time_increment\": %.9g, \"ranges\": [",
                ok ? "true" : "false", numEchos, (double)msg.angle_min, (double)msg.angle_increment, (double)msg.angle_max,
                (double)msg.scan_time, (double)msg.time_increment);
    for (size_t i = 0; i < msg.ranges.size(); i++)
      std::printf("%s%.9g", i ? ", " : "", (double)msg.ranges[i]);
    std::printf("], \"intensities\": [");
    for (size_t i = 0; i < msg.intensities.size(); i++)
      std::printf("%s%.9g", i ? ", " : "", (double)msg.intensities[i]);
    std::printf("]}\n");
  }
  return 0;
}
